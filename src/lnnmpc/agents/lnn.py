"""LNN-TD-MPC2 (thesis §4.3, Algorithms 1–5): the eight ``{cfc,ltc}-{zp,op}-{det,stoch}`` agents.

TD-MPC2 (:mod:`lnnmpc.agents.tdmpc2`) with its per-observation encoder replaced by a liquid history encoder
(:mod:`lnnmpc.agents.lnn_model`). Only the world-model loss and acting differ; the update step (model and
policy optimisers, policy loss on stop-gradient latents with the running Q scale, Polyak target Q) is
TD-MPC2's, inherited.

Replay record per step t (:meth:`LNNTDMPC2.replay_record`): obs o_t, action a_t, reward r_t, Δt_t, the encoder
state h_{t−1} the actor held before reading o_t, and a_{t−1} (zeros at an episode start). A training window has
``burn_in + horizon + 1`` = T + H + 1 records (time-major, never crossing an episode). World-model loss:

* burn-in: from the stored state h_{−1} of the window's first record, the encoder reads records 0..T−1;
  the resulting state passes through ``stop_gradient`` (no gradient through the burn-in, Algorithm 1 line 2);
* the encoder then reads records T..T+H with gradients (truncated BPTT): latents z_0..z_H (z = h, or its
  SimNorm head's output with ``latent_head="simnorm"``);
* prediction (weighted ρ^t, averaged over the H steps, coefficient ``consistency_coef``), from (z_t, a_t):
  ZP det ‖ẑ_{t+1} − sg(z_{t+1})‖² (mean over dims); ZP stoch the Gaussian NLL of sg(z_{t+1}); OP det
  ‖ô_{t+1} − o_{t+1}‖²; OP stoch the Gaussian NLL of o_{t+1} with free bits: per step and sample,
  max(NLL, ``free_bits``). NLLs are in nats per dimension (mean over dims, like the MSEs). Each dimension's
  NLL is weighted by stop_gradient(σ^(2β)) (β-NLL, ``nll_beta``; β = 0 is the plain NLL of the thesis): with
  β = 1 the mean gets the gradient of ½ × the squared error, as in the det variants, instead of one 1/σ²
  times larger (400× at σ = 0.05), while σ still goes to the NLL's optimum;
* reward and Q: TD-MPC2's two-hot soft cross-entropies at z_0..z_{H−1} (the encoder's latents), Q against
  TD(λ) targets (:func:`lnnmpc.agents.returns.lambda_returns`) with bootstrap values
  v_{t+1} = min of 2 random Polyak target heads at (sg(z_{t+1}), π(sg(z_{t+1}))).
* ``rollout_steps`` K > 1 (this project's extension; K = 1 is the thesis): the same three losses are also taken
  on the planner's own latents, open loop from every position of the window, as TD-MPC2 takes them on its
  rollouts. Depth 0 is the encoder's latents z_t; depth k the planner's transition applied k times,
  ẑ^k_t = T(ẑ^{k−1}_{t−1}, a_{t−1}) (the predictor's mean; OP through the encoder with Δt = 1, Algorithm 5),
  for t = k..H−1. Depth k ∈ 0..K−1 predicts the next latent / observation of its positions and carries the
  reward and Q losses of its positions; each loss is the mean over its depths, gradients flow through the
  rollout. The depths are stacked on the time axis for one pass of the heads and losses (fewer kernels; with
  K = 1 bit for bit the unstacked loss; with K > 1 one Q-dropout mask over the stack instead of one per depth).
  With K = 1 the planner scores action sequences with heads that never saw a predicted latent, and its
  H_plan = 10 steps go that far off the encoder's latents.
* ``rollout_stride`` S (speed; default 1, 3 on walker: registry.LNN_TASK_DEFAULTS): the depths k >= 1 start
  only from every S-th position of the window (0, S, 2S, ...), so depth k has ceil((H − k) / S) positions
  instead of H − k; depth 0 keeps all H. The heads and losses over the stacked depths are most of an update's
  time (62% for walker with K = 3 on an H100: benchmarks/results/README.md, run 15), and K = 3 stacks 93
  positions at S = 1, 53 at S = 3. Each depth's loss
  is still the mean over its positions, weighted ρ^(t − k) by its positions t (ρ = 1 by default).

Acting (:meth:`LNNTDMPC2.act`): the encoder reads [o_t, a_{t−1}] with Δt_t, then MPPI plans from h_t. The
planner's transition (Algorithm 4 / 5) samples the stochastic predictor: ZP rolls ẑ_{t+1} ~ f(z_t, a_t); OP
predicts ô_{t+1} ~ f(z_t, a_t) and feeds it through the encoder with Δt = 1, ẑ_{t+1} = φ(z_t, [ô_{t+1}, a_t], 1).
The planning latent is ``{"z": (N,), "key": (2,) uint32}``; the key drives the predictor's noise (the samples of
one planning call share it, common random numbers).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from lnnmpc.agents import math as M
from lnnmpc.agents.lnn_model import HEAD_ONLY_SETTINGS, LNNModelConfig, LNNWorldModel, encoder_input, make_cell
from lnnmpc.agents.mppi import MPPIConfig, PlanningModel, mppi_plan
from lnnmpc.agents.returns import lambda_returns
from lnnmpc.agents.tdmpc2 import TDMPC2, AgentState, TDMPC2Config, make_optimizers
from lnnmpc.nets import unroll
from lnnmpc.nets.common import check_int_at_least


@dataclasses.dataclass(frozen=True)
class LNNConfig(TDMPC2Config):
    """LNN-TD-MPC2 hyper-parameters: TD-MPC2's, with the thesis's changes (H = 32, ρ = 1, planning horizon 10)
    and burn-in T, TD(λ) and free bits. T = 10 and λ = 0.95 are this project's choice (the thesis gives none).

    ``free_bits`` (OP stoch only; the thesis's eq. 4.16 floor, value not given) is in nats per observation
    dimension. A dimension predicted exactly has NLL log σ + ½ log 2π: −2.08 at the default ``min_sigma`` 0.05,
    −1.38 at σ = 0.1, −0.92 at σ = 0.25. The default −2.0 stops the loss only once the average dimension is
    predicted at about the σ floor; −1 (this project's first default) stopped cartpole-swingup's OP-stoch
    model at σ ≈ 0.14 within 16K steps (the loss sat on the floor from then on, and the agent scored ~250 where
    OP det reached ~800: `experiments/results/variants-cartpole-swingup-50k-h100`).

    ``nll_beta`` β ∈ [0, 1] weights the stochastic variants' per-dimension NLL by stop_gradient(σ^(2β))
    (β-NLL, Seitzer et al. 2022). The plain NLL (β = 0) scales the mean's gradient by 1/σ²: with σ at its floor
    it outweighed the reward and value losses in the shared encoder (gradient norms 10–1,000 against 0.2–5 for
    the det variants in that run, clipped at 20). The default β = 1 gives the mean the det variants' gradient
    scale; β = 0 reproduces the thesis's objective.
    """

    model: LNNModelConfig
    planner: MPPIConfig = MPPIConfig(horizon=10)
    horizon: int = 32
    rho: float = 1.0
    burn_in: int = 10
    lambda_: float = 0.95
    free_bits: float = -2.0  # floor of the OP-stoch per-step NLL, nats per dimension
    nll_beta: float = 1.0  # β-NLL weight stop_gradient(σ^(2β)) of the stochastic variants' NLL; 0 = plain NLL
    rollout_steps: int = 1  # K: depths of open-loop model losses (module docstring); 1 = the thesis
    rollout_stride: int = 1  # S: depths >= 1 start from every S-th window position only (module docstring)
    # Encoder time steps per lax.scan iteration in the update (speed only; >= T + H + 1 leaves no loop). No faster
    # on an H100 for walker (12.65 ms rolled, 12.87 fully unrolled: benchmarks/results/README.md, run 13).
    scan_unroll: int = 1
    # Windows whose burn-in reaches back past their episode's start (the encoder restarting at its first record),
    # so an episode's first T records are learning steps too; False (the thesis): windows never cross an episode,
    # and those records are only ever burn-in.
    learn_episode_starts: bool = False

    def __post_init__(self):
        super().__post_init__()
        check_int_at_least("burn_in", self.burn_in, 0)
        check_int_at_least("rollout_steps", self.rollout_steps, 1)
        check_int_at_least("rollout_stride", self.rollout_stride, 1)
        if self.rollout_stride > self.horizon:
            raise ValueError(f"rollout_stride ({self.rollout_stride}) must be <= horizon ({self.horizon}): the "
                             "rollouts start every rollout_stride positions of the window")
        check_int_at_least("scan_unroll", self.scan_unroll, 1)
        if self.rollout_steps > self.horizon:
            raise ValueError(f"rollout_steps ({self.rollout_steps}) must be <= horizon ({self.horizon}): depth k "
                             "has horizon - k positions in a window")
        if not 0 <= self.lambda_ <= 1:
            raise ValueError(f"lambda_ must be in [0, 1], got {self.lambda_!r}")
        if not 0 <= self.nll_beta <= 1:
            raise ValueError(f"nll_beta must be in [0, 1], got {self.nll_beta!r}")


    def inactive_fields(self) -> set[str]:
        """Flattened config keys (``model.min_sigma``) that do not affect this variant's computation."""
        unused = super().inactive_fields()
        if not self.model.stochastic:
            unused |= {"free_bits", "nll_beta", "model.min_sigma", "model.max_sigma"}
        elif self.model.objective == "zp":
            unused.add("free_bits")
        if self.rollout_steps == 1:
            unused.add("rollout_stride")
        if self.burn_in == 0:  # windows then start at their episode's start at the earliest
            unused.add("learn_episode_starts")
        if self.model.latent_head == "none":
            unused |= {f"model.{name}" for name in ("simnorm_dim", *HEAD_ONLY_SETTINGS)}
        return unused


@struct.dataclass
class LNNCarry:
    """Acting carry of one environment: encoder state h_{t−1} (N,), previous action (A,), plan mean (H_plan, A)."""

    h: jax.Array
    prev_action: jax.Array
    plan_mean: jax.Array


def lnn_config(name: str, obs_dim: int, action_dim: int, planner: MPPIConfig, **model) -> LNNConfig:
    """Config of the agent ``name`` = ``"{cfc,ltc}-{zp,op}-{det,stoch}"``; ``model`` overrides model fields."""
    parts = name.split("-")
    if len(parts) != 3 or parts[2] not in ("det", "stoch"):
        raise ValueError(f"bad LNN agent name {name!r}; expected {{cfc,ltc}}-{{zp,op}}-{{det,stoch}}")
    cell, objective, kind = parts
    return LNNConfig(model=LNNModelConfig(obs_dim, action_dim, cell=cell, objective=objective,
                                          stochastic=kind == "stoch", **model),
                     planner=planner)


class LNNTDMPC2(TDMPC2):
    """Pure functions of an LNN-TD-MPC2 agent (build once; all methods jit and vmap over seeds).

    Acting goes through the protocol's :meth:`act`; the inherited ``plan(state, obs, prev_mean, ...)`` plans from
    a one-observation history with the mean transition (no encoder carry, no predictor noise).
    """

    def __init__(self, config: LNNConfig):
        self.config = config
        self.model = LNNWorldModel(config.model)
        self.cell = make_cell(config.model)
        self.model_tx, self.policy_tx = make_optimizers(config)

    # -------------------------------------------------------------------------------------- encoder
    def encode_sequence(self, params, h0: jax.Array, obs: jax.Array, prev_action: jax.Array,
                        dt: jax.Array, resets: jax.Array | None = None) -> jax.Array:
        """Encoder states (T, B, N) after each step, from h0 (B, N), obs (T, B, d), prev_action (T, B, A), dt (T, B);
        ``resets`` (T, B) bool restarts a sample from zeros (the initial carry's state) before that step."""
        inputs = encoder_input(self.config.model, obs, prev_action)
        return unroll(self.cell, {"params": params["encoder"]}, h0, inputs, dt, resets,
                      scan_unroll=self.config.scan_unroll).states

    def latents(self, params, batch: dict) -> jax.Array:
        """z_0..z_H (H + 1, B, N) of a window: burn-in from the stored state under stop_gradient, then BPTT.

        With ``learn_episode_starts`` the window's records that start an episode (``batch["first"]`` (T + H + 1,
        B) bool, from ``replay_sample``; only within positions 0..T) restart the encoder from their stored state
        h_{−1} (the acting carry's reset, zeros), so the records before them change nothing."""
        T = self.config.burn_in
        h = batch["h_prev"][0]
        first = batch["first"] if self.config.learn_episode_starts else None
        if T:
            with jax.named_scope("encoder_burn_in"):
                h = self.encode_sequence(params, h, batch["obs"][:T], batch["prev_action"][:T],
                                         batch["dt"][:T], resets=None if first is None else first[:T])[-1]
        if first is not None:  # an episode that starts at the window's first learning record
            h = jnp.where(first[T][:, None], batch["h_prev"][T], h)
        h = jax.lax.stop_gradient(h)
        with jax.named_scope("encoder_window"):
            hs = self.encode_sequence(params, h, batch["obs"][T:], batch["prev_action"][T:], batch["dt"][T:])
        return self.latent_of(params, hs, batch["obs"][T:])

    def latent_of(self, params, h: jax.Array, obs: jax.Array) -> jax.Array:
        """The latents z (..., Z) of encoder states h (..., N) that have just read obs (..., d): h itself (Z = N),
        or its SimNorm head's output (of [h, o] with ``latent_obs_skip``)."""
        if self.config.model.latent_head == "none":
            return h
        return self._apply(params, h, obs, method="latent")

    # -------------------------------------------------------------------------------------- losses
    def prediction_loss(self, params, z: jax.Array, action: jax.Array,
                        target: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Per-step prediction loss (H,) of the next latent / observation ``target`` (H, B, D) from (z_t, a_t),
        and per-step diagnostics (H,): for the stochastic variants ``prediction_nll`` (the plain NLL per
        dimension, after the free-bits floor), ``prediction_sigma`` (mean σ) and, OP only, ``free_bits_floored``
        (fraction of samples on the floor, which pass no gradient)."""
        mean, sigma = self._apply(params, z, action, method="predict")
        if sigma is None:
            return jnp.mean((mean - target) ** 2, axis=(1, 2)), {}
        op = self.config.model.objective == "op"
        loss, nll, floored = M.gaussian_nll_loss(mean, sigma, target, self.config.nll_beta,
                                                 self.config.free_bits if op else None)  # (H, B) each
        info = {"prediction_sigma": sigma.mean(axis=(1, 2))}
        if op:
            info["free_bits_floored"] = floored.mean(axis=1)
        info["prediction_nll"] = nll.mean(axis=1)
        return loss.mean(axis=1), info

    def world_model_loss(self, params, target_q, batch, key):
        """Scalar loss and (stop-gradient latents (H + 1, B, N), metrics) for a window (module docstring)."""
        cfg = self.config
        T, H = cfg.burn_in, cfg.horizon
        action, reward = batch["action"][T:T + H], batch["reward"][T:T + H]
        k_pi, k_heads, k_drop = jax.random.split(key, 3)
        zs = self.latents(params, batch)
        next_z = jax.lax.stop_gradient(zs[1:])
        with jax.named_scope("td_targets"):
            next_action = self._policy_sample(params, next_z, k_pi).action
            next_q = self._q_values(params, next_z, next_action, self._two_heads(k_heads), q_params=target_q)
            td_target = jax.lax.stop_gradient(lambda_returns(reward, self._target_value(next_q), cfg.gamma,
                                                             cfg.lambda_))
        target = next_z if cfg.model.objective == "zp" else batch["obs"][T + 1:]

        # Every depth's latents (depth k >= 1: positions k + s for the rollout starts s = 0, S, 2S, ... <= H-1-k;
        # depth 0: all H positions) and inputs stacked on the time axis, so the heads and losses run once for all
        # K depths (one set of kernels, not K), then are split back per depth.
        K, S = cfg.rollout_steps, cfg.rollout_stride
        counts = [H] + [len(range(0, H - k, S)) for k in range(1, K)]  # positions of each depth
        z, by_depth = zs[:-1][::S], [zs[:-1]]
        for k in range(1, K):
            with jax.named_scope("model_losses"):
                z = self._apply(params, z[:counts[k]], action[k - 1::S][:counts[k]], method="transition")
            by_depth.append(z)
        stack = lambda x: jnp.concatenate([x] + [x[k::S][:counts[k]] for k in range(1, K)])
        with jax.named_scope("model_losses"):
            per_step = self._step_losses(params, jnp.concatenate(by_depth), stack(action), stack(reward),
                                         stack(td_target), stack(target), k_drop)
            positions = lambda a, b: jax.tree_util.tree_map(lambda x: x[..., a:b], per_step)  # time axis last
            ends = [sum(counts[:k]) for k in range(K + 1)]
            depths = [self._depth_average(positions(a, b), 1 if k == 0 else S)
                      for k, (a, b) in enumerate(zip(ends[:-1], ends[1:], strict=True))]
        losses = {name: sum(d[0][name] for d in depths) / len(depths) for name in depths[0][0]}
        total = (cfg.consistency_coef * losses["prediction_loss"] + cfg.reward_coef * losses["reward_loss"]
                 + cfg.value_coef * losses["value_loss"])
        metrics = {**losses, "total_loss": total, **depths[0][1]}
        if cfg.rollout_steps > 1:
            metrics["rollout_prediction_loss"] = depths[-1][0]["prediction_loss"]
        return total, (jax.lax.stop_gradient(zs), metrics)

    def _step_losses(self, params, z, action, reward, td_target, target, key) -> dict:
        """Per-position losses of latents z (n, B, N) with their actions (n, B, A), rewards and TD targets (n, B)
        and prediction targets (n, B, D): ``prediction`` (n,), ``reward`` (n,), ``value`` (num_q, n) and the
        prediction's diagnostics ``info`` {name: (n,)}; one Q-head dropout mask from ``key``."""
        cfg, num_bins = self.config, self.config.model.num_bins
        prediction, info = self.prediction_loss(params, z, action, target)
        reward_ce = M.soft_cross_entropy(self._apply(params, z, action, method="reward"), reward, num_bins,
                                         cfg.vmin, cfg.vmax).mean(axis=1)
        q_logits = self._apply(params, z, action, False, method="q", rngs={"dropout": key})
        value_ce = M.soft_cross_entropy(q_logits, td_target[None], num_bins, cfg.vmin, cfg.vmax).mean(axis=2)
        return {"prediction": prediction, "reward": reward_ce, "value": value_ce, "info": info}

    def _depth_average(self, per_step: dict, spacing: int = 1) -> tuple[dict, dict]:
        """One depth's losses from its :meth:`_step_losses` (n positions, ``spacing`` steps apart): each
        ρ^(spacing·j)-weighted and averaged over the n positions; returns (losses, the prediction's diagnostics
        averaged the same way)."""
        cfg, n = self.config, per_step["prediction"].shape[0]
        weights = M.discounted_weights(n, cfg.rho ** spacing)
        average = lambda x: jnp.sum(weights * x) / n
        losses = {"prediction_loss": average(per_step["prediction"]), "reward_loss": average(per_step["reward"]),
                  # one division, as before rollout_steps existed: K = 1 stays bit-for-bit the old loss
                  "value_loss": jnp.sum(weights * per_step["value"].sum(axis=0)) / (n * cfg.model.num_q)}
        return losses, {k: average(v) for k, v in per_step["info"].items()}

    # ------------------------------------------------------------ acting protocol (agents/registry.py)
    @property
    def sequence_length(self) -> int:
        """Replay records per training window: burn-in T + H + 1."""
        return self.config.burn_in + self.config.horizon + 1

    @property
    def sequence_lead(self) -> int:
        """Records at a window's start that may precede its episode: the burn-in T with ``learn_episode_starts``
        (the encoder restarts at the episode's first record), else 0."""
        return self.config.burn_in if self.config.learn_episode_starts else 0

    def initial_carry(self) -> LNNCarry:
        c = self.config
        return LNNCarry(h=jnp.zeros((c.model.hidden_size,)), prev_action=jnp.zeros((c.model.action_dim,)),
                        plan_mean=jnp.zeros((c.planner.horizon, c.model.action_dim)))

    def replay_record(self, obs, action, reward, dt, carry: LNNCarry) -> dict:
        """obs (d,), action (A,), reward (), dt (), h_prev (N,) = h_{t−1}, prev_action (A,) = a_{t−1}."""
        return {"obs": obs, "action": action, "reward": reward, "dt": dt, "h_prev": carry.h,
                "prev_action": carry.prev_action}

    def _start(self, carry: LNNCarry, first_step) -> LNNCarry:
        first = jnp.asarray(first_step)
        return jax.tree_util.tree_map(lambda init, x: jnp.where(first, init, x), self.initial_carry(), carry)

    def _encode_one(self, params, carry: LNNCarry, obs, dt) -> jax.Array:
        """h_t (N,) = φ(h_{t−1}, [o_t, a_{t−1}], Δt_t) for one environment."""
        return self._apply(params, carry.h[None], obs[None], carry.prev_action[None], jnp.reshape(dt, (1,)),
                           method="encode_step")[0]

    def observe(self, state: AgentState, carry: LNNCarry, obs, dt, action, *, first_step) -> LNNCarry:
        """The encoder reads the step; the chosen ``action`` becomes a_{t−1} of the next step."""
        carry = self._start(carry, first_step)
        return carry.replace(h=self._encode_one(state.params, carry, obs, dt), prev_action=action)

    def planning_model(self, params) -> PlanningModel:
        """Per-sample world model for MPPI over latents ``{"z": (N,), "key": (2,) uint32}`` (Algorithms 4, 5).

        The stochastic variants' transitions draw their noise from the latent's key, which MPPI copies to every
        sample: all candidate action sequences of one act call are scored under the same noise path (common
        random numbers, so they are ranked by their actions, not by their draws); each act call draws a new path.
        """
        cfg = self.config

        def dynamics(latent, a):
            k_noise, k_next = jax.random.split(jax.random.wrap_key_data(latent["key"]))
            noise = jax.random.normal(k_noise, (cfg.model.target_dim,)) if cfg.model.stochastic else None
            z_next = self._apply(params, latent["z"], a, noise, method="transition")
            return {"z": z_next, "key": jax.random.key_data(k_next)}

        return PlanningModel(
            dynamics=dynamics,
            reward=lambda lat, a: self._predicted_reward(params, lat["z"], a),
            value=lambda lat, a, k: self._planning_value(params, lat["z"], a, k),
            policy=lambda lat, k: self._policy_sample(params, lat["z"], k).action,
        )

    def act_planned(self, state: AgentState, carry: LNNCarry, obs: jax.Array, dt: jax.Array, key: jax.Array, *,
                    explore: bool, first_step: jax.Array, explore_noise: jax.Array | None = None
                    ) -> tuple[jax.Array, LNNCarry, dict]:
        """Encode o_t (d,) after Δt_t (), plan with MPPI from h_t; returns (action (A,), next carry, the planner's
        ``info``: :func:`mppi_plan`'s, the final ``std`` (horizon, A), ...); ``explore_noise`` (A,):
        :func:`mppi_plan`'s. The inherited :meth:`act` is this without the info."""
        params = state.params
        carry = self._start(carry, first_step)
        h = self._encode_one(params, carry, obs, dt)
        k_plan, k_model = jax.random.split(key)
        latent = {"z": self.latent_of(params, h, obs), "key": jax.random.key_data(k_model)}
        action, mean, info = mppi_plan(self.config.planner, self.planning_model(params),
                                       latent, carry.plan_mean, k_plan, explore=explore, first_step=first_step,
                                       explore_noise=explore_noise)
        return action, LNNCarry(h=h, prev_action=action, plan_mean=mean), info

    def act_prior(self, state: AgentState, carry: LNNCarry, obs: jax.Array, dt: jax.Array, key: jax.Array, *,
                  explore: bool, first_step: jax.Array) -> tuple[jax.Array, LNNCarry]:
        """:meth:`act` with the policy prior in place of MPPI: (action (A,), next carry); the encoder reads the step
        as in :meth:`act`, the plan mean passes through."""
        carry = self._start(carry, first_step)
        h = self._encode_one(state.params, carry, obs, dt)
        action = self.prior_action(state.params, self.latent_of(state.params, h, obs), key, explore=explore)
        return action, LNNCarry(h=h, prev_action=action, plan_mean=carry.plan_mean)
