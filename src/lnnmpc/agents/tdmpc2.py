"""TD-MPC2 (the baseline agent): losses, one compiled update step and one compiled act step.

Update on a time-major batch of H + 1 replay records (obs (H+1, B, d), action (H+1, B, A), reward (H+1, B); the
last record's action and reward are unused), following TD-MPC2:

* targets: next latents ``z'_t = enc(o_{t+1})`` (no gradient); TD targets ``r_t + γ Q̄(z'_t, π(z'_t))`` with
  Q̄ the min of 2 random heads of the Polyak target network (their mean with ``target_q="mean"``, not TD-MPC2's);
* world model: latent rollout ``ẑ_{t+1} = d(ẑ_t, a_t)`` from ``ẑ_0 = enc(o_0)``; consistency MSE to ``z'_t``,
  reward and Q soft cross-entropies on two-hot targets at ``ẑ_0..ẑ_{H-1}``, each step weighted ρ^t and averaged
  over the horizon (Q also over heads); total ``20·consistency + 0.1·reward + 0.1·value``; Adam with the encoder's
  learning rate × 0.3 and the gradient clipped at norm 20 over all world-model parameters together;
* policy: on stop-gradient latents ``ẑ_0..ẑ_H``, ``-(1e-4·entropy + Q/scale)`` with Q the mean of 2 random online
  heads and ``scale`` TD-MPC2's running 5–95 percentile range of Q at t = 0;
* the target Q network follows the online one with τ = 0.01.

Acting plans with MPPI (:mod:`lnnmpc.agents.mppi`) through the latent model; the two Q heads averaged for the
terminal value are drawn anew for each MPPI iteration's value estimate, as TD-MPC2 does.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct
from flax.traverse_util import path_aware_map

from lnnmpc.agents import math as M
from lnnmpc.agents.mppi import TERMINAL_Q, MPPIConfig, PlanningModel, combine_terminal_q, mppi_plan
from lnnmpc.agents.tdmpc2_model import WorldModel, WorldModelConfig, q_logits_of_heads


@dataclasses.dataclass(frozen=True)
class TDMPC2Config:
    """Agent hyper-parameters (TD-MPC2's published defaults)."""

    model: WorldModelConfig
    planner: MPPIConfig = MPPIConfig()
    horizon: int = 3
    rho: float = 0.5
    gamma: float = 0.99
    tau: float = 0.01
    lr: float = 3e-4
    encoder_lr_scale: float = 0.3
    grad_clip_norm: float = 20.0
    # True: the world model's gradient (encoder and the rest together) is clipped by its one global norm, as
    # TD-MPC2 clips all model parameters at once; False: each learning-rate group on its own norm (before 2026-11-23).
    joint_grad_clip: bool = True
    # True: each optimiser runs Adam over one flat vector of all parameters (optax.flatten) and the learning-rate
    # groups become per-leaf scales: the same updates (up to float32 rounding) in fewer, larger kernels
    # (benchmarks/update_kernels.py: -22% fusions on the CPU; on an H100, walker-run, 4 seeds: 7.00 ms per update
    # against 7.62, benchmarks/results/h100-run10-*); needs joint_grad_clip. False: Adam per leaf.
    flat_optimizer: bool = True
    consistency_coef: float = 20.0
    reward_coef: float = 0.1
    value_coef: float = 0.1
    entropy_coef: float = 1e-4
    vmin: float = -10.0
    vmax: float = 10.0
    # Learning-rate decay (not TD-MPC2's, whose rate is constant; lr_final_scale = 1, the default, keeps it so):
    # every rate (the encoder's, the rest's, the policy's) is constant up to update lr_decay_begin, falls linearly
    # to lr_final_scale times itself at update lr_decay_end, and stays there. Updates are counted per seed: one
    # per agent step, and action repeat 2 makes ~100K updates of a 200K-environment-step run (the seed phase's
    # burst included). Meant to quiet a converged policy's late swings (late evaluations that collapse).
    lr_decay_begin: int = 0
    lr_decay_end: int = 0
    lr_final_scale: float = 1.0
    # How the TD targets combine the two target Q heads drawn: their minimum (TD-MPC2: a pessimistic target) or
    # their mean (not TD-MPC2's). The minimum's bias compounds along the bootstrap chain (roughly its per-step bias
    # / (1 - gamma)); the acrobot recipe's critic values its own prior's return 12.7 too low on average and ~10x
    # too low from starts hanging at rest (experiments/RESULTS.md [80]).
    target_q: str = "min"

    def __post_init__(self):
        if not isinstance(self.horizon, int) or self.horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {self.horizon!r}")
        for name in ("rho", "gamma", "tau"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)!r}")
        for name in ("lr", "encoder_lr_scale", "grad_clip_norm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        _check_lr_decay(self.lr_decay_begin, self.lr_decay_end, self.lr_final_scale)
        if self.target_q not in TERMINAL_Q:
            raise ValueError(f"target_q={self.target_q!r} is invalid; expected one of {', '.join(TERMINAL_Q)} (how "
                             "the TD targets combine the two target Q heads drawn)")
        if self.flat_optimizer and not self.joint_grad_clip:
            raise ValueError("flat_optimizer=True needs joint_grad_clip=True (one flat vector has one global norm; "
                             "per-group clipping is the per-leaf optimiser's)")

    def inactive_fields(self) -> set[str]:
        """Flattened config keys that do not affect the computation (the decay's updates without a decay)."""
        return {"lr_decay_begin", "lr_decay_end"} if self.lr_final_scale == 1.0 else set()


def _check_lr_decay(begin, end, final_scale) -> None:
    for name, value in (("lr_decay_begin", begin), ("lr_decay_end", end)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name} must be an integer >= 0 (an update count), got {value!r}")
    if isinstance(final_scale, bool) or not isinstance(final_scale, int | float) or not 0.0 < final_scale <= 1.0:
        raise ValueError(f"lr_final_scale must be in (0, 1] (1: a constant learning rate), got {final_scale!r}")
    if final_scale < 1.0 and end <= begin:
        raise ValueError(f"lr_decay_end={end} must exceed lr_decay_begin={begin} when lr_final_scale={final_scale} "
                         "< 1 (the decay runs from update lr_decay_begin to update lr_decay_end)")


def learning_rate(config: TDMPC2Config, scale: float = 1.0) -> float | optax.Schedule:
    """``config.lr · scale``, or without a decay configured (``lr_final_scale`` 1) that float; otherwise a schedule
    of the optimiser's update count: constant to ``lr_decay_begin``, linear to ``lr_final_scale`` times the rate at
    ``lr_decay_end``, constant after."""
    if config.lr_final_scale == 1.0:
        return config.lr * scale
    return optax.linear_schedule(config.lr * scale, config.lr * scale * config.lr_final_scale,
                                 transition_steps=config.lr_decay_end - config.lr_decay_begin,
                                 transition_begin=config.lr_decay_begin)


@struct.dataclass
class AgentState:
    """Everything the agent learns: parameters, Polyak target Q heads, optimiser states, Q scale, update count."""

    params: Any
    target_q: Any
    model_opt: Any
    policy_opt: Any
    scale: M.ScaleState
    updates: jax.Array


def _labels(params, rule):
    return path_aware_map(lambda path, _: rule(path[0]), params)


def clip_jointly(grads: dict, max_norm: float, frozen: tuple[str, ...] = ()) -> dict:
    """Scales every gradient but the ``frozen`` top-level entries by min(1, max_norm / ‖g‖), ‖g‖ the global
    norm over those same entries (torch's clip_grad_norm_ over a module's parameters)."""
    norm = optax.tree.norm({k: v for k, v in grads.items() if k not in frozen})
    factor = jnp.minimum(1.0, max_norm / jnp.maximum(norm, 1e-12))
    return {k: v if k in frozen else jax.tree.map(lambda g: g * factor, v) for k, v in grads.items()}


# Top-level parameter groups trained at the encoder's learning rate (× encoder_lr_scale): the encoder, and an LNN
# agent's latent head (the projection TD-MPC2's encoder ends with).
ENCODER_PARAMS = ("encoder", "latent_head")


def make_optimizers(config: TDMPC2Config) -> tuple[optax.GradientTransformation, optax.GradientTransformation]:
    """(world-model optimiser: all but the policy head; policy optimiser: the policy head only)."""
    clip = optax.clip_by_global_norm(config.grad_clip_norm)
    model_groups = lambda params: _labels(params, lambda top: "encoder" if top in ENCODER_PARAMS else
                                          "frozen" if top == "policy_head" else "rest")
    policy_groups = lambda params: _labels(params, lambda top: "policy" if top == "policy_head" else "frozen")
    if config.flat_optimizer:
        # Adam(lr · s) = s · Adam(lr): the groups' learning rates become scales after one flat Adam; frozen
        # gradients are zeroed first so that they neither enter the clip's norm nor move (zero moments, zero step).
        keep, zero = optax.identity(), optax.set_to_zero()
        model_tx = optax.chain(
            optax.multi_transform({"encoder": keep, "rest": keep, "frozen": zero}, model_groups),
            optax.flatten(optax.chain(clip, optax.adam(learning_rate(config)))),
            optax.multi_transform({"encoder": optax.scale(config.encoder_lr_scale), "rest": keep, "frozen": zero},
                                  model_groups))
        policy_tx = optax.chain(optax.multi_transform({"policy": keep, "frozen": zero}, policy_groups),
                                optax.flatten(optax.chain(clip, optax.adam(learning_rate(config), eps=1e-5))))
        return model_tx, policy_tx
    model_tx = optax.multi_transform(
        {"encoder": optax.chain(clip, optax.adam(learning_rate(config, config.encoder_lr_scale))),
         "rest": optax.chain(clip, optax.adam(learning_rate(config))), "frozen": optax.set_to_zero()}, model_groups)
    policy_tx = optax.multi_transform(
        {"policy": optax.chain(clip, optax.adam(learning_rate(config), eps=1e-5)), "frozen": optax.set_to_zero()},
        policy_groups)
    return model_tx, policy_tx


class TDMPC2:
    """Pure functions of the agent (build once; all methods jit and vmap over seeds)."""

    def __init__(self, config: TDMPC2Config):
        self.config = config
        self.model = WorldModel(config.model)
        self.model_tx, self.policy_tx = make_optimizers(config)

    # -------------------------------------------------------------------------------------- state
    def init(self, key: jax.Array) -> AgentState:
        c = self.config.model
        params = self.model.init(key, jnp.zeros((c.obs_dim,)), jnp.zeros((c.action_dim,)))["params"]
        return AgentState(params=params, target_q=params["q_heads"], model_opt=self.model_tx.init(params),
                          policy_opt=self.policy_tx.init(params), scale=M.ScaleState.create(),
                          updates=jnp.zeros((), jnp.int32))

    # --------------------------------------------------------------------------------- components
    def _apply(self, params, *args, method, **kwargs):
        return self.model.apply({"params": params}, *args, method=method, **kwargs)

    def _q_values(self, params, z, action, heads, key=None, q_params=None):
        """Q of the chosen heads (2,) -> (2, ...), only those heads computed; dropout on when ``key`` is given;
        ``q_params`` (the target heads) in place of ``params["q_heads"]``."""
        q_params = params["q_heads"] if q_params is None else q_params
        logits = q_logits_of_heads(self.config.model, q_params, heads, z, action, dropout_key=key)
        return M.two_hot_inv(logits, self.config.model.num_bins, self.config.vmin, self.config.vmax)

    def _predicted_reward(self, params, z, action):
        """The reward head's prediction for (z, action), decoded from its two-hot logits: scalar per sample."""
        return M.two_hot_inv(self._apply(params, z, action, method="reward"), self.config.model.num_bins,
                             self.config.vmin, self.config.vmax)

    def _planning_value(self, params, z, action, key):
        """MPPI's terminal value of (z, action): the two Q heads ``key`` draws, combined by ``planner.terminal_q``
        (their mean as TD-MPC2, or their minimum): scalar per sample."""
        return combine_terminal_q(self._q_values(params, z, action, self._two_heads(key)),
                                  self.config.planner.terminal_q)

    def _policy_sample(self, params, z, key):
        mean, raw = self._apply(params, z, method="policy")
        return M.sample_tanh_gaussian(key, mean, raw)

    def _two_heads(self, key):
        return jax.random.choice(key, self.config.model.num_q, (2,), replace=False)

    def _target_value(self, target_heads):
        """The bootstrap value of the two target heads' Q (2, ...) -> (...): their minimum (TD-MPC2) or, with
        ``target_q="mean"``, their mean."""
        return combine_terminal_q(target_heads, self.config.target_q)

    # -------------------------------------------------------------------------------------- losses
    def world_model_loss(self, params, target_q, batch, key):
        """Scalar loss and metrics for a batch (see the module docstring)."""
        cfg, num_bins = self.config, self.config.model.num_bins
        obs, action, reward = batch["obs"], batch["action"][:-1], batch["reward"][:-1]
        H = action.shape[0]
        k_pi, k_heads, k_drop = jax.random.split(key, 3)
        next_z = jax.lax.stop_gradient(self._apply(params, obs[1:], method="encode"))
        next_action = self._policy_sample(params, next_z, k_pi).action
        target_q = self._q_values(params, next_z, next_action, self._two_heads(k_heads), q_params=target_q)
        td_target = jax.lax.stop_gradient(reward + cfg.gamma * self._target_value(target_q))

        def rollout(z, a):
            z_next = self._apply(params, z, a, method="next")
            return z_next, z_next

        z0 = self._apply(params, obs[0], method="encode")
        _, z_pred = jax.lax.scan(rollout, z0, action)  # (H, B, L)
        zs = jnp.concatenate([z0[None], z_pred])  # (H + 1, B, L)
        weights = M.discounted_weights(H, cfg.rho)
        consistency = jnp.sum(weights * jnp.mean((z_pred - next_z) ** 2, axis=(1, 2))) / H
        reward_logits = self._apply(params, zs[:-1], action, method="reward")
        reward_ce = M.soft_cross_entropy(reward_logits, reward, num_bins, cfg.vmin, cfg.vmax).mean(axis=1)
        q_logits = self._apply(params, zs[:-1], action, False, method="q", rngs={"dropout": k_drop})
        value_ce = M.soft_cross_entropy(q_logits, td_target[None], num_bins, cfg.vmin, cfg.vmax).mean(axis=2)
        reward_loss = jnp.sum(weights * reward_ce) / H
        value_loss = jnp.sum(weights * value_ce.sum(axis=0)) / (H * self.config.model.num_q)
        total = cfg.consistency_coef * consistency + cfg.reward_coef * reward_loss + cfg.value_coef * value_loss
        metrics = {"consistency_loss": consistency, "reward_loss": reward_loss, "value_loss": value_loss,
                   "total_loss": total}
        return total, (jax.lax.stop_gradient(zs), metrics)

    def policy_loss(self, params, zs, scale, key):
        """Policy objective on stop-gradient latents zs (H + 1, B, L); returns (loss, (new scale, metrics))."""
        cfg = self.config
        k_pi, k_heads, k_drop = jax.random.split(key, 3)
        sample = self._policy_sample(params, zs, k_pi)
        q = self._q_values(params, zs, sample.action, self._two_heads(k_heads), key=k_drop).mean(axis=0)
        scale = M.update_scale(scale, jax.lax.stop_gradient(q[0]))
        q = M.apply_scale(scale, q)
        weights = M.discounted_weights(zs.shape[0], cfg.rho)
        per_step = -(cfg.entropy_coef * sample.scaled_entropy + q).mean(axis=1)
        loss = jnp.mean(weights * per_step)
        return loss, (scale, {"policy_loss": loss, "q_scale": scale.value, "entropy": -sample.log_prob.mean()})

    # -------------------------------------------------------------------------------------- update
    def update(self, state: AgentState, batch: dict, key: jax.Array) -> tuple[AgentState, dict]:
        """One TD-MPC2 update on ``batch`` (obs (H+1, B, d), action (H+1, B, A), reward (H+1, B))."""
        # The named scopes only label the compiled ops (benchmarks/profile_update.py sums kernel time by them).
        k_model, k_policy = jax.random.split(key)
        with jax.named_scope("world_model_grad"):
            grads, (zs, metrics) = jax.grad(self.world_model_loss, has_aux=True)(
                state.params, state.target_q, batch, k_model)
        with jax.named_scope("model_optimizer"):
            metrics["grad_norm"] = optax.tree.norm(grads)
            if self.config.joint_grad_clip:  # the groups' own clips (make_optimizers) then never bind
                grads = clip_jointly(grads, self.config.grad_clip_norm, frozen=("policy_head",))
            updates, model_opt = self.model_tx.update(grads, state.model_opt, state.params)
            params = optax.apply_updates(state.params, updates)
        with jax.named_scope("policy_grad"):
            pi_grads, (scale, pi_metrics) = jax.grad(self.policy_loss, has_aux=True)(
                params, zs, state.scale, k_policy)
        with jax.named_scope("policy_optimizer"):
            updates, policy_opt = self.policy_tx.update(pi_grads, state.policy_opt, params)
            params = optax.apply_updates(params, updates)
            target_q = M.polyak(state.target_q, params["q_heads"], self.config.tau)
        new_state = AgentState(params=params, target_q=target_q, model_opt=model_opt, policy_opt=policy_opt,
                               scale=scale, updates=state.updates + 1)
        rate = learning_rate(self.config)
        if callable(rate):  # a decaying rate is logged (train.csv's lr): the one this update used
            metrics["lr"] = rate(state.updates)
        return new_state, {**metrics, **pi_metrics}

    # ------------------------------------------------------------ acting protocol (agents/registry.py)
    @property
    def sequence_length(self) -> int:
        """Replay records per training window: H + 1."""
        return self.config.horizon + 1

    @property
    def sequence_lead(self) -> int:
        """Records at a window's start that may precede its episode (``replay_sample``'s ``lead``): none."""
        return 0

    def initial_carry(self) -> jax.Array:
        """Acting carry of one environment at an episode start: the planner's warm start (plan horizon, A)."""
        return jnp.zeros((self.config.planner.horizon, self.config.model.action_dim))

    def replay_record(self, obs, action, reward, dt, carry) -> dict:
        """What replay stores per step: obs (d,), action (A,), reward () (the MLP encoder needs no Δt or state)."""
        return {"obs": obs, "action": action, "reward": reward}

    def observe(self, state: AgentState, carry, obs, dt, action, *, first_step) -> jax.Array:
        """Carry after an externally chosen action (seed phase): the warm start stays as it is."""
        return carry

    def act(self, state: AgentState, carry: jax.Array, obs: jax.Array, dt: jax.Array, key: jax.Array, *,
            explore: bool, first_step: jax.Array, explore_noise: jax.Array | None = None
            ) -> tuple[jax.Array, jax.Array]:
        """Protocol act: MPPI action (A,) for one observation (d,) and the next carry (the plan mean);
        ``explore_noise`` (A,): :func:`mppi_plan`'s. :meth:`act_planned` without the planner's info (a subclass that
        acts otherwise overrides ``act_planned`` alone)."""
        return self.act_planned(state, carry, obs, dt, key, explore=explore, first_step=first_step,
                                explore_noise=explore_noise)[:2]

    def act_planned(self, state: AgentState, carry: jax.Array, obs: jax.Array, dt: jax.Array, key: jax.Array, *,
                    explore: bool, first_step: jax.Array, explore_noise: jax.Array | None = None
                    ) -> tuple[jax.Array, jax.Array, dict]:
        """:meth:`act` plus the planner's ``info`` (:func:`mppi_plan`'s: the final ``std`` (horizon, A), ...)."""
        return self.plan(state, obs, carry, key, explore=explore, first_step=first_step, explore_noise=explore_noise)

    def act_prior(self, state: AgentState, carry: jax.Array, obs: jax.Array, dt: jax.Array, key: jax.Array, *,
                  explore: bool, first_step: jax.Array) -> tuple[jax.Array, jax.Array]:
        """:meth:`act` without MPPI: the policy prior's action (A,) from the latent the planner would plan from
        (tanh of its mean; a sample when ``explore``), TD-MPC2's ``act(mpc=False)``. The carry passes through."""
        return self.prior_action(state.params, self._apply(state.params, obs, method="encode"), key,
                                 explore=explore), carry

    def prior_action(self, params, z: jax.Array, key: jax.Array, *, explore: bool) -> jax.Array:
        """The policy prior's action (..., A) at latents z (..., Z): tanh of its mean, or a sample (``explore``)."""
        sample = self._policy_sample(params, z, key)
        return sample.action if explore else sample.mean_action

    # ----------------------------------------------------------------------------------------- act
    def planning_model(self, params) -> PlanningModel:
        """The world model as MPPI's per-sample functions of a latent z (latent_dim,): the latent dynamics, the
        reward head, the terminal value (``planner.terminal_q`` over the two Q heads drawn) and the policy prior."""
        return PlanningModel(
            dynamics=lambda z, a: self._apply(params, z, a, method="next"),
            reward=lambda z, a: self._predicted_reward(params, z, a),
            value=lambda z, a, k: self._planning_value(params, z, a, k),
            policy=lambda z, k: self._policy_sample(params, z, k).action,
        )

    def plan(self, state: AgentState, obs: jax.Array, prev_mean: jax.Array, key: jax.Array, *, explore: bool,
             first_step: jax.Array, explore_noise: jax.Array | None = None
             ) -> tuple[jax.Array, jax.Array, dict]:
        """MPPI action (A,) for one observation (d,); returns (action, plan mean (horizon, A), :func:`mppi_plan`'s
        info)."""
        params = state.params
        z = self._apply(params, obs, method="encode")
        return mppi_plan(self.config.planner, self.planning_model(params), z, prev_mean, key,
                         explore=explore, first_step=first_step, explore_noise=explore_noise)
