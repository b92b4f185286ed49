"""TD-MPC2's world model in Flax (official architecture and defaults).

Components (``z`` is the SimNorm latent (L,), ``a`` the action (A,)):

* encoder   o -> z: MLP (enc_dim x max(num_enc_layers - 1, 1)) -> latent_dim, LayerNorm, SimNorm(groups of 8)
* dynamics  [z, a] -> z': MLP (mlp_dim x 2) -> latent_dim, LayerNorm, SimNorm
* reward    [z, a] -> logits (num_bins,): MLP (mlp_dim x 2) -> num_bins, zero-initialised output layer
* policy    z -> (mean, raw log std) (A,) each: MLP (mlp_dim x 2) -> 2A
* Q         [z, a] -> logits (num_q, num_bins): an ensemble of num_q MLPs (dropout 0.01 after the first
  layer), zero-initialised output layers

Hidden layers are Dense -> (Dropout) -> LayerNorm -> Mish, as TD-MPC2's ``NormedLinear`` (whose SimNorm output
layers are Dense -> LayerNorm -> SimNorm); kernels are normal(0.02), biases zero. Sizes follow TD-MPC2's
``MODEL_SIZE`` table (1M and 5M parameters).
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp

from lnnmpc.agents.math import simnorm

MODEL_SIZES = {
    1: {"enc_dim": 256, "mlp_dim": 384, "latent_dim": 128, "num_enc_layers": 2, "num_q": 2},
    5: {"enc_dim": 256, "mlp_dim": 512, "latent_dim": 512, "num_enc_layers": 2, "num_q": 5},
}


@dataclasses.dataclass(frozen=True)
class WorldModelConfig:
    """Architecture of the world model; :meth:`from_size` fills the size-dependent fields."""

    obs_dim: int
    action_dim: int
    enc_dim: int = 256
    mlp_dim: int = 512
    latent_dim: int = 512
    num_enc_layers: int = 2
    num_q: int = 5
    simnorm_dim: int = 8
    num_bins: int = 101
    q_dropout: float = 0.01
    # LayerNorm between the encoder's and the dynamics' last Dense and their SimNorm, as TD-MPC2's NormedLinear
    # output layers have (False: the layout of runs before 2026-11-23).
    simnorm_layer_norm: bool = True

    def __post_init__(self):
        for name in ("obs_dim", "action_dim", "enc_dim", "mlp_dim", "latent_dim", "num_enc_layers",
                     "simnorm_dim", "num_bins"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not isinstance(self.num_q, int) or self.num_q < 2:
            raise ValueError(f"num_q must be an integer >= 2 (targets use the min of 2 heads), got {self.num_q!r}")
        if self.latent_dim % self.simnorm_dim:
            raise ValueError(f"latent_dim {self.latent_dim} must be divisible by simnorm_dim {self.simnorm_dim}")
        if not 0 <= self.q_dropout < 1:
            raise ValueError(f"q_dropout must be in [0, 1), got {self.q_dropout!r}")

    @classmethod
    def from_size(cls, obs_dim: int, action_dim: int, model_size: int = 5, **overrides) -> WorldModelConfig:
        if model_size not in MODEL_SIZES:
            raise ValueError(f"unknown model_size {model_size!r}; known: {', '.join(map(str, MODEL_SIZES))}")
        return cls(obs_dim=obs_dim, action_dim=action_dim, **{**MODEL_SIZES[model_size], **overrides})


def mish(x: jax.Array) -> jax.Array:
    return x * jnp.tanh(jax.nn.softplus(x))


# TD-MPC2 draws weights from torch's trunc_normal_(std=0.02), whose cut is at ±2 (absolute, i.e. ±100σ): in
# effect N(0, 0.02²). flax's truncated_normal(0.02) cuts at ±2σ and has std 0.0176.
_KERNEL_INIT = nn.initializers.normal(0.02)


class SplitDense(nn.Module):
    """``nn.Dense`` over the concatenation of several inputs without building it: inputs ``xs`` (tuple of
    (..., d_i)) -> sum_i x_i @ kernel[rows of i] + bias, (..., features).

    Same parameters as ``nn.Dense(features)`` on ``concatenate(xs, -1)`` ('kernel' (sum d_i, features), 'bias'),
    drawn from the same initialisers, so under the same module name they take the same values. Why: the
    concatenation of a (..., 512) latent and a (..., 1) action is one more pass over the latents and leaves a
    513-wide operand that the GPU multiplies with unaligned kernels; in the MPPI rollouts with 8 seeds on an H200
    the concatenations before the dynamics alone cost 0.36 ms of a 5.27 ms act step (benchmark run 27). Inputs
    at most ``NARROW`` wide (actions) are applied as that many broadcast products, elementwise work XLA fuses
    into the sum instead of a matrix product of its own.
    """

    features: int
    kernel_init: nn.initializers.Initializer = _KERNEL_INIT
    NARROW = 8

    @nn.compact
    def __call__(self, xs: tuple[jax.Array, ...]) -> jax.Array:
        dims = [x.shape[-1] for x in xs]
        kernel = self.param("kernel", self.kernel_init, (sum(dims), self.features), jnp.float32)
        out = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
        start = 0
        for x, d in zip(xs, dims, strict=True):
            rows = kernel[start:start + d]
            if d <= self.NARROW:
                for k in range(d):
                    out = out + x[..., k:k + 1] * rows[k]
            else:
                out = x @ rows + out
            start += d
        return out


class MLP(nn.Module):
    """Hidden NormedLinear layers then a Dense output; optional SimNorm output (after a LayerNorm when
    ``output_layer_norm``), zero-initialised output. The input is one array (..., d) or a tuple of arrays
    (..., d_i) that the first layer reads as their concatenation (:class:`SplitDense`)."""

    hidden: tuple[int, ...]
    out_dim: int
    simnorm_dim: int = 0  # 0: no SimNorm on the output
    dropout: float = 0.0  # after the first hidden Dense
    zero_output: bool = False
    output_layer_norm: bool = False

    @nn.compact
    def __call__(self, x: jax.Array | tuple[jax.Array, ...], deterministic: bool = True) -> jax.Array:
        for i, width in enumerate(self.hidden):
            # explicit names: the layers keep nn.Dense's automatic ones (Dense_0, Dense_1, ...) either way
            dense = SplitDense if isinstance(x, tuple) else nn.Dense
            x = dense(width, kernel_init=_KERNEL_INIT, name=f"Dense_{i}")(x)
            if i == 0 and self.dropout > 0:
                x = nn.Dropout(self.dropout, deterministic=deterministic)(x)
            x = mish(nn.LayerNorm(epsilon=1e-5)(x))
        init = nn.initializers.zeros if self.zero_output else _KERNEL_INIT
        dense = SplitDense if isinstance(x, tuple) else nn.Dense  # a tuple still, only without hidden layers
        x = dense(self.out_dim, kernel_init=init, name=f"Dense_{len(self.hidden)}")(x)
        if self.output_layer_norm:
            x = nn.LayerNorm(epsilon=1e-5)(x)
        return simnorm(x, self.simnorm_dim) if self.simnorm_dim else x


def q_ensemble(config, num_heads: int) -> nn.Module:
    """``num_heads`` Q heads as one module over a leading head axis: input (num_heads, ..., L + A), or the tuple
    ((num_heads, ..., L), (num_heads, ..., A)) read as its concatenation, -> logits (num_heads, ..., num_bins);
    parameters with leaves (num_heads, ...). ``config``: a model config with
    ``mlp_dim``, ``num_bins`` and ``q_dropout``.

    The heads take their input with the head axis in front (the callers broadcast it): with a shared input
    (in_axes=None) the first layer's output comes out (..., num_heads, mlp_dim) and vmap moves the head axis to
    the front with a transpose of every hidden activation, forward and backward (on an H100 the update's longest
    kernels, run 19). Same parameters, dropout masks and outputs either way."""
    ensemble = nn.vmap(MLP, variable_axes={"params": 0}, split_rngs={"params": True, "dropout": True},
                       in_axes=(0, None), axis_size=num_heads)
    return ensemble((config.mlp_dim, config.mlp_dim), config.num_bins, dropout=config.q_dropout, zero_output=True)


def _per_head(xs: tuple[jax.Array, ...], n: int) -> tuple[jax.Array, ...]:
    """Each input broadcast to a leading head axis of ``n``: the ensemble's input."""
    return tuple(jnp.broadcast_to(x, (n, *x.shape)) for x in xs)


def q_logits_of_heads(config, q_params, heads: jax.Array, z: jax.Array, action: jax.Array,
                      dropout_key: jax.Array | None = None) -> jax.Array:
    """Q logits (k, ..., num_bins) of the heads ``heads`` (k,) of the ensemble ``q_params`` (leaves (num_q, ...),
    the model's ``q_heads``) at (z (..., L), action (..., A)), computing only those k heads: the targets, the
    policy objective and the planner use 2 of TD-MPC2's 5, which the full ensemble would compute 2.5 times over.
    Equal to ``WorldModel.q(z, action)[heads]`` without dropout; with ``dropout_key`` each chosen head draws its
    own mask (from other random numbers than the full ensemble's). Where ``heads`` names as many heads as there
    are (the liquid agents' 2 of 2), the ensemble runs as it is and its outputs are put in that order (gathering
    the parameters would only add kernels)."""
    every = heads.shape[0] == jax.tree_util.tree_leaves(q_params)[0].shape[0]
    run = q_params if every else jax.tree_util.tree_map(lambda p: p[heads], q_params)
    n = heads.shape[0]
    rngs = {"dropout": dropout_key} if dropout_key is not None else {}
    logits = q_ensemble(config, n).apply({"params": run}, _per_head((z, action), n), dropout_key is None, rngs=rngs)
    return logits[heads] if every else logits


class WorldModel(nn.Module):
    """TD-MPC2 world model; call its methods with ``model.apply(variables, ..., method=...)``."""

    config: WorldModelConfig

    def setup(self):
        c = self.config
        normed = c.simnorm_layer_norm
        self.encoder = MLP((c.enc_dim,) * max(c.num_enc_layers - 1, 1), c.latent_dim, c.simnorm_dim,
                           output_layer_norm=normed)
        self.dynamics = MLP((c.mlp_dim, c.mlp_dim), c.latent_dim, c.simnorm_dim, output_layer_norm=normed)
        self.setup_heads()

    def setup_heads(self):
        """Reward, policy and Q heads (called from ``setup``; subclasses with another encoder reuse it)."""
        c = self.config
        self.reward_head = MLP((c.mlp_dim, c.mlp_dim), c.num_bins, zero_output=True)
        self.policy_head = MLP((c.mlp_dim, c.mlp_dim), 2 * c.action_dim)
        self.q_heads = q_ensemble(c, c.num_q)

    def encode(self, obs: jax.Array) -> jax.Array:
        """obs (..., obs_dim) -> z (..., latent_dim)."""
        return self.encoder(obs)

    def next(self, z: jax.Array, action: jax.Array) -> jax.Array:
        """(z (..., L), a (..., A)) -> next latent (..., L)."""
        return self.dynamics((z, action))

    def reward(self, z: jax.Array, action: jax.Array) -> jax.Array:
        """Reward logits (..., num_bins)."""
        return self.reward_head((z, action))

    def policy(self, z: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(mean, raw log std), each (..., A); squash and scale them with :mod:`lnnmpc.agents.math`."""
        mean, raw_log_std = jnp.split(self.policy_head(z), 2, axis=-1)
        return mean, raw_log_std

    def q(self, z: jax.Array, action: jax.Array, deterministic: bool = True) -> jax.Array:
        """Q logits of every head (num_q, ..., num_bins); dropout is active when not ``deterministic``."""
        return self.q_heads(_per_head((z, action), self.config.num_q), deterministic)

    def __call__(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, ...]:
        """Touches every component (used by ``init``)."""
        z = self.encode(obs)
        return self.next(z, action), self.reward(z, action), self.policy(z), self.q(z, action)


def init_world_model(config: WorldModelConfig, key: jax.Array):
    """Parameters of a fresh model: ``{'params': ...}``."""
    model = WorldModel(config)
    return model, model.init(key, jnp.zeros((config.obs_dim,)), jnp.zeros((config.action_dim,)))


def count_parameters(variables) -> int:
    return sum(x.size for x in jax.tree_util.tree_leaves(variables))
