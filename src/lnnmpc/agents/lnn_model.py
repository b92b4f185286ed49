"""LNN-TD-MPC2's world model in Flax (thesis §4.3): a liquid history encoder plus TD-MPC2's heads.

Components (``h`` the encoder state (B, N), N = ``hidden_size``; ``a`` actions (B, A); ``o`` observations (B, d)):

* encoder φ: a CfC or LTC cell (:mod:`lnnmpc.nets`) over x_t = [o_t, a_{t−1}] with time input Δt_t,
  ``h_t = φ(h_{t−1}, x_t, Δt_t)``. The latent is the state itself, ``z_t = h_t`` (latent size = LNN hidden
  size = 64, Table 4.1): by default (``latent_head="none"``) no projection and no SimNorm follow the cell. The
  cells' states are already bounded (CfC default mode: a gated mix of two tanh's, in [−1, 1]; LTC: the
  semi-implicit Euler update keeps the potentials within the span of the previous state, v_leak and the reversal
  potentials), and the OP planner (Algorithm 5) must carry the cell state anyway. ``latent_head="simnorm"``
  (ZP det only; SPEC §4's "a linear projection and SimNorm may follow") reads the latent off the state as
  TD-MPC2's encoder ends, ``z_t = SimNorm(LayerNorm(W h_t + b))`` (``latent_size`` units, N unless set,
  groups of ``simnorm_dim``), and the predictor ends the same way, so that the planner rolls latents on
  TD-MPC2's simplices (512 wide in TD-MPC2's 5M model); the encoder still carries h. With
  ``latent_obs_skip=True`` the head also reads the observation the state has just taken in,
  ``z_t = SimNorm(LayerNorm(W [h_t, o_t] + b))`` (o_t transformed as the cell's input): a skip past the
  cell's N-wide state, as TD-MPC2's encoder reads o_t directly (not in the thesis). ``latent_head_hidden=W``
  puts one hidden layer (Dense -> LayerNorm -> Mish, W wide) before the head's output layer, the shape of
  TD-MPC2's encoder (256 wide in its 5M model).
  ``input_transform="symlog"`` feeds the cell sign(o)·log(1 + |o|) instead of o (the thesis feeds o; walker's
  joint velocities reach ±50 and saturate the CfC backbone, see :data:`INPUT_TRANSFORMS`). The LTC runs
  ``ode_unfolds`` (6) hybrid-Euler sub-steps and reads no output map (``output_mapping="none"``).
* predictor f: an MLP (``mlp_dim`` × 2, NormedLinear + Mish) on [z, a] predicting the next latent (ZP) or
  the next observation (OP): deterministic (the prediction) or a diagonal Gaussian (mean, σ) with
  σ = clip(softplus(raw), min_sigma, max_sigma). Means are unbounded (dm_control observations are).
* reward, policy and Q heads exactly as TD-MPC2's (:class:`lnnmpc.agents.tdmpc2_model.WorldModel`), on z.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp

from lnnmpc.agents.math import symlog
from lnnmpc.agents.tdmpc2_model import MLP, WorldModel
from lnnmpc.nets import CFC_MODES, CfCCell, LTCCell
from lnnmpc.nets.common import check_choice, check_fraction, check_int_at_least

CELLS = ("cfc", "ltc")
OBJECTIVES = ("zp", "op")
# What the encoder does to an observation before the cell reads it: "none" (the thesis) or "symlog"
# (sign(o)·log(1+|o|), DreamerV3's squashing of vector inputs; identity near 0, logarithmic for large |o|).
# The OP predictor still predicts raw observations; the planner squashes its predictions the same way.
INPUT_TRANSFORMS = ("none", "symlog")
# What turns the encoder state h into the latent z: "none" (z = h, this project's default) or "simnorm"
# (Dense -> LayerNorm -> SimNorm, as TD-MPC2's encoder output; self-predictive deterministic variants only).
LATENT_HEADS = ("none", "simnorm")
# Settings of latent_head="simnorm" that must keep their defaults without the head (simnorm_dim, read only by the
# head, may keep any value).
HEAD_ONLY_SETTINGS = ("latent_size", "latent_obs_skip", "latent_head_hidden")


@dataclasses.dataclass(frozen=True)
class LNNModelConfig:
    """Architecture (defaults: the thesis's light configuration, Table 4.1)."""

    obs_dim: int
    action_dim: int
    cell: str = "cfc"  # "cfc" or "ltc"
    objective: str = "zp"  # "zp" (self-predictive) or "op" (observation-predictive)
    stochastic: bool = False  # Gaussian predictor (NLL) instead of a deterministic one (MSE)
    hidden_size: int = 64  # LNN hidden size = latent size (unless latent_head's latent_size)
    mlp_dim: int = 192
    num_q: int = 2
    num_bins: int = 101
    q_dropout: float = 0.01
    cfc_mode: str = "default"
    backbone_units: int = 128  # CfC backbone width (ncps default)
    backbone_layers: int = 1
    ode_unfolds: int = 6  # LTC Euler sub-steps per input step
    min_sigma: float = 0.05  # bounds of the stochastic predictor's σ
    max_sigma: float = 5.0
    input_transform: str = "none"  # one of INPUT_TRANSFORMS
    latent_head: str = "none"  # one of LATENT_HEADS
    simnorm_dim: int = 8  # SimNorm group size of latent_head="simnorm"
    latent_size: int = 0  # width of latent_head="simnorm"'s latent; 0: hidden_size
    latent_obs_skip: bool = False  # latent_head="simnorm" reads [h_t, o_t] instead of h_t
    latent_head_hidden: int = 0  # width of one hidden layer in latent_head="simnorm"; 0: none (linear head)

    def __post_init__(self):
        for name in ("obs_dim", "action_dim", "hidden_size", "mlp_dim", "num_bins", "backbone_units",
                     "ode_unfolds", "simnorm_dim"):
            check_int_at_least(name, getattr(self, name), 1)
        check_int_at_least("backbone_layers", self.backbone_layers, 0)
        check_int_at_least("latent_size", self.latent_size, 0)
        check_int_at_least("latent_head_hidden", self.latent_head_hidden, 0)
        check_int_at_least("num_q", self.num_q, 2)
        check_choice("cell", self.cell, CELLS)
        check_choice("objective", self.objective, OBJECTIVES)
        check_choice("stochastic", self.stochastic, (False, True))
        check_choice("cfc_mode", self.cfc_mode, CFC_MODES)
        check_choice("input_transform", self.input_transform, INPUT_TRANSFORMS)
        check_choice("latent_head", self.latent_head, LATENT_HEADS)
        check_choice("latent_obs_skip", self.latent_obs_skip, (False, True))
        check_fraction("q_dropout", self.q_dropout)
        if self.latent_head == "simnorm":
            if self.objective != "zp" or self.stochastic:
                raise ValueError(f"latent_head='simnorm' needs a self-predictive deterministic agent (*-zp-det), "
                                 f"got objective={self.objective!r}, stochastic={self.stochastic!r}")
            if self.latent_dim % self.simnorm_dim:
                size = f"latent_size={self.latent_size}" if self.latent_size else f"hidden_size={self.hidden_size}"
                raise ValueError(f"latent_head='simnorm' needs a latent size divisible by simnorm_dim, got {size}, "
                                 f"simnorm_dim={self.simnorm_dim}")
        else:
            set_without_head = [f"{name}={getattr(self, name)}" for name in HEAD_ONLY_SETTINGS if getattr(self, name)]
            if set_without_head:
                raise ValueError(f"{set_without_head[0]} needs latent_head='simnorm': without a head the latent "
                                 f"is the encoder state (hidden_size={self.hidden_size})")
        if not 0 < self.min_sigma <= self.max_sigma:
            raise ValueError(f"need 0 < min_sigma <= max_sigma, got min_sigma={self.min_sigma!r}, "
                             f"max_sigma={self.max_sigma!r}")

    @property
    def latent_dim(self) -> int:
        """Size of the latent z: N (z = h), or the SimNorm head's ``latent_size`` when set."""
        return self.latent_size or self.hidden_size

    @property
    def target_dim(self) -> int:
        """Size of what the predictor predicts: the latent (ZP) or the observation (OP)."""
        return self.latent_dim if self.objective == "zp" else self.obs_dim


def make_cell(config: LNNModelConfig) -> nn.Module:
    """The encoder cell (an unbound module: also used with :func:`lnnmpc.nets.unroll`)."""
    if config.cell == "cfc":
        return CfCCell(config.hidden_size, mode=config.cfc_mode, backbone_units=config.backbone_units,
                       backbone_layers=config.backbone_layers)
    return LTCCell(config.hidden_size, ode_unfolds=config.ode_unfolds, output_mapping="none")


def transformed_obs(config: LNNModelConfig, obs: jax.Array) -> jax.Array:
    """Observations (..., d) as the encoder reads them (``input_transform``)."""
    return symlog(obs) if config.input_transform == "symlog" else obs


def encoder_input(config: LNNModelConfig, obs: jax.Array, prev_action: jax.Array) -> jax.Array:
    """The cell's input x = [transform(o), a_prev] (..., d + A) from obs (..., d) and prev_action (..., A)."""
    return jnp.concatenate([transformed_obs(config, obs), prev_action], axis=-1)


def gaussian_params(raw: jax.Array, min_sigma: float, max_sigma: float) -> tuple[jax.Array, jax.Array]:
    """(..., 2D) predictor output -> (mean (..., D), σ (..., D)) with σ = clip(softplus(raw), min, max)."""
    mean, raw_sigma = jnp.split(raw, 2, axis=-1)
    return mean, jnp.clip(jax.nn.softplus(raw_sigma), min_sigma, max_sigma)


class LNNWorldModel(WorldModel):
    """LNN-TD-MPC2 world model; call its methods with ``model.apply(variables, ..., method=...)``.

    Parameter groups: ``encoder`` (the cell), ``predictor``, and TD-MPC2's ``reward_head``, ``policy_head``,
    ``q_heads`` (so TD-MPC2's optimiser split applies: encoder learning rate × 0.3, policy head apart).
    """

    config: LNNModelConfig

    def setup(self):
        c = self.config
        self.encoder = make_cell(c)
        simnorm = c.simnorm_dim if c.latent_head == "simnorm" else 0
        if simnorm:
            hidden = (c.latent_head_hidden,) if c.latent_head_hidden else ()
            self.latent_head = MLP(hidden, c.latent_dim, simnorm, output_layer_norm=True)
        self.predictor = MLP((c.mlp_dim, c.mlp_dim), c.target_dim * (2 if c.stochastic else 1), simnorm,
                             output_layer_norm=bool(simnorm))
        self.setup_heads()

    def latent(self, h: jax.Array, obs: jax.Array | None = None) -> jax.Array:
        """The latent z (..., Z) the heads and the planner read, from encoder states h (..., N) and, with
        ``latent_obs_skip``, the observations (..., d) they have just read (required then)."""
        c = self.config
        if c.latent_head == "none":
            return h
        if c.latent_obs_skip:
            if obs is None:
                raise ValueError("latent_obs_skip=True: the latent needs the observation the state has read")
            h = jnp.concatenate([h, transformed_obs(c, obs)], axis=-1)
        return self.latent_head(h)

    def encode_step(self, h: jax.Array, obs: jax.Array, prev_action: jax.Array, dt: jax.Array) -> jax.Array:
        """One encoder step: h (B, N), obs (B, d), prev_action (B, A), dt (B,) or (B, 1) -> h' (B, N)."""
        new_h, _ = self.encoder(h, encoder_input(self.config, obs, prev_action), dt)
        return new_h

    def predict(self, z: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array | None]:
        """(z (..., N), a (..., A)) -> (prediction or mean (..., D), σ (..., D) or None when deterministic)."""
        out = self.predictor((z, action))
        if not self.config.stochastic:
            return out, None
        return gaussian_params(out, self.config.min_sigma, self.config.max_sigma)

    def transition(self, z: jax.Array, action: jax.Array, noise: jax.Array | None = None) -> jax.Array:
        """The planner's transition T(z, a) -> z' (..., N) (Algorithm 4 for ZP, 5 for OP).

        The prediction is the predictor's mean, or ``mean + σ * noise`` when stochastic and ``noise`` (..., D)
        (standard normal) is given. ZP: z' is the prediction; OP: the predicted observation goes through the
        encoder with Δt = 1, z' = φ(z, [ô, a], 1).
        """
        mean, sigma = self.predict(z, action)
        pred = mean if sigma is None or noise is None else mean + sigma * noise
        if self.config.objective == "zp":
            return pred
        return self._encode_flat(z, pred, action)

    def encode(self, obs: jax.Array) -> jax.Array:
        """Latent (..., N) of a one-observation history (zero state, zero previous action, Δt = 1)."""
        zeros = jnp.zeros((*obs.shape[:-1], self.config.hidden_size), obs.dtype)
        return self.latent(self._encode_flat(zeros, obs, jnp.zeros((*obs.shape[:-1], self.config.action_dim),
                                                                   obs.dtype)), obs)

    def next(self, z: jax.Array, action: jax.Array) -> jax.Array:
        """Mean transition (..., N) (TD-MPC2's ``next``; used when planning without the predictor's noise)."""
        return self.transition(z, action)

    def _encode_flat(self, h: jax.Array, obs: jax.Array, prev_action: jax.Array) -> jax.Array:
        """:meth:`encode_step` with Δt = 1 over any leading axes (..., N)."""
        flat = lambda x: x.reshape(-1, x.shape[-1])
        new_h = self.encode_step(flat(h), flat(obs), flat(prev_action), jnp.ones((flat(h).shape[0],), h.dtype))
        return new_h.reshape(h.shape)

    def __call__(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, ...]:
        """Touches every component (used by ``init``); obs (d,), action (A,)."""
        h = self.encode_step(jnp.zeros((1, self.config.hidden_size)), obs[None], action[None], jnp.ones((1,)))[0]
        z = self.latent(h, obs)
        return self.predict(z, action), self.reward(z, action), self.policy(z), self.q(z, action)
