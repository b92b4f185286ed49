"""MPPI planner with a policy prior, as TD-MPC2 plans (thesis Algorithm 3), written as pure JAX.

The caller supplies the world model as a :class:`PlanningModel` of pure per-sample functions (parameters closed
over); latents may be arbitrary pytrees. The planner vectorises them over samples with ``jax.vmap``, runs the
horizon and the MPPI iterations as ``lax.scan``s, and is jit- and vmap-friendly (``config`` and ``explore`` are
static; ``first_step`` may be traced).

Semantics (TD-MPC2 ``plan`` / ``_estimate_value``):

* ``num_policy_trajectories`` action sequences come from rolling the policy prior through the dynamics once per
  call; they are kept fixed across iterations.
* The mean starts from the previous solution shifted one step earlier (last step zero; all zeros on the first
  step of an episode), the std at ``max_std``.
* Each iteration samples ``num_samples - num_policy_trajectories`` Gaussian sequences clipped to [-1, 1], scores all
  sequences by ``G = sum_t gamma^t r_t + gamma^H Q(z_H, pi(z_H))``, keeps the top ``num_elites`` and refits the
  mean and std with weights ``exp(temperature * (G - max G))`` (std clipped to [min_std, max_std]).
* The returned action is the first action of one elite drawn with probability proportional to its weight, plus
  ``std[0] * N(0, 1)`` exploration noise (clipped) when ``explore``; ``explore_min_std`` > 0 (not TD-MPC2's) puts a
  floor under that noise's scale, ``max(std[0], explore_min_std)``: a planner whose value has seen no reward can
  settle on a behaviour of its own with a small std (on cartpole-swingup-sparse, barely swinging the pole: 0.6
  turns per episode against 2.8 for a planner ranking at random; ``experiments/scripts/stuck_seed_exploration.py``),
  and its exploration shrinks with it.
* The terminal value's two Q heads are averaged (TD-MPC2) or, with ``terminal_q="min"`` (not TD-MPC2's), their
  minimum is taken (:func:`combine_terminal_q`; the agents apply it in their ``planning_model``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from lnnmpc.nets.common import check_int_at_least

Latent = Any  # an arbitrary pytree of arrays (one sample, no batch axis)


class PlanningModel(NamedTuple):
    """Per-sample pure functions of the world model (no batch axis; the planner vmaps them).

    dynamics(z, a) -> z' (same pytree structure as z); reward(z, a) -> scalar; value(z, a, key) -> scalar
    terminal Q, ``key`` shared by all samples of one estimate (TD-MPC2 draws the Q heads it averages anew for each
    value estimate, i.e. each MPPI iteration); policy(z, key) -> a, one sample from the policy prior (actions in
    [-1, 1]).
    """

    dynamics: Callable[[Latent, jax.Array], Latent]
    reward: Callable[[Latent, jax.Array], jax.Array]
    value: Callable[[Latent, jax.Array, jax.Array], jax.Array]
    policy: Callable[[Latent, jax.Array], jax.Array]


def _check_positive(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 < value < float("inf"):
        raise ValueError(f"{name}={value!r} is invalid; expected a finite number > 0")


TERMINAL_Q = ("mean", "min")


def combine_terminal_q(q_heads: jax.Array, terminal_q: str) -> jax.Array:
    """The terminal value from the drawn Q heads' values (heads, ...) -> (...): their mean (TD-MPC2) or, with
    ``terminal_q="min"``, their minimum, which values a state by its most pessimistic head, so that imagined
    trajectories into states where the heads disagree (rare in the replay, where a critic's over-estimate lives)
    score lower. The agents' TD targets combine their two target heads with it too (``target_q``, minimum by
    default there)."""
    return jnp.min(q_heads, axis=0) if terminal_q == "min" else jnp.mean(q_heads, axis=0)


@dataclasses.dataclass(frozen=True)
class MPPIConfig:
    """MPPI hyperparameters (TD-MPC2 defaults)."""

    horizon: int = 3
    iterations: int = 6
    num_samples: int = 512
    num_policy_trajectories: int = 24
    num_elites: int = 64
    temperature: float = 0.5
    min_std: float = 0.05
    max_std: float = 2.0
    gamma: float = 0.99
    explore_min_std: float = 0.0  # floor of the exploration noise's scale in exploring calls (0: std[0] alone)
    terminal_q: str = "mean"  # how the agent combines the 2 Q heads of the terminal value: "mean" (TD-MPC2) or "min"
    unroll: bool = False  # unroll the scans: no faster on an H100 (act 2.97 vs 2.85 ms rolled), slower to compile

    def __post_init__(self) -> None:
        check_int_at_least("horizon", self.horizon, 1)
        check_int_at_least("iterations", self.iterations, 1)
        check_int_at_least("num_samples", self.num_samples, 1)
        check_int_at_least("num_policy_trajectories", self.num_policy_trajectories, 0)
        check_int_at_least("num_elites", self.num_elites, 1)
        if self.num_policy_trajectories > self.num_samples:
            raise ValueError(
                f"num_policy_trajectories={self.num_policy_trajectories} exceeds num_samples={self.num_samples}"
            )
        if self.num_elites > self.num_samples:
            raise ValueError(f"num_elites={self.num_elites} exceeds num_samples={self.num_samples}")
        _check_positive("temperature", self.temperature)
        _check_positive("min_std", self.min_std)
        _check_positive("max_std", self.max_std)
        if self.min_std > self.max_std:
            raise ValueError(f"min_std={self.min_std!r} exceeds max_std={self.max_std!r}")
        _check_positive("gamma", self.gamma)
        if self.gamma > 1.0:
            raise ValueError(f"gamma={self.gamma!r} is invalid; expected a number in (0, 1]")
        if self.terminal_q not in TERMINAL_Q:
            raise ValueError(f"terminal_q={self.terminal_q!r} is invalid; expected one of {', '.join(TERMINAL_Q)}")
        floor = self.explore_min_std
        if isinstance(floor, bool) or not isinstance(floor, int | float) or not 0.0 <= floor < float("inf"):
            raise ValueError(f"explore_min_std={floor!r} is invalid; expected a finite number >= 0 (0: the "
                             "planner's std alone, as TD-MPC2)")


def shift_mean(prev_mean: jax.Array, first_step: jax.Array | bool) -> jax.Array:
    """Warm start: ``prev_mean`` moved one step earlier with a zero last step, or all zeros when ``first_step``."""
    shifted = jnp.concatenate([prev_mean[1:], jnp.zeros_like(prev_mean[:1])], axis=0)
    return jnp.where(jnp.asarray(first_step), jnp.zeros_like(prev_mean), shifted)


def _repeat(z: Latent, n: int) -> Latent:
    """Stack ``n`` copies of a single latent along a new leading axis."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (n, *jnp.shape(x))), z)


def _policy_batch(model: PlanningModel, z: Latent, key: jax.Array, n: int) -> jax.Array:
    return jax.vmap(model.policy)(z, jax.random.split(key, n))


def policy_trajectories(config: MPPIConfig, model: PlanningModel, z0: Latent, key: jax.Array) -> jax.Array:
    """Roll the policy prior through the dynamics: (horizon, num_policy_trajectories, act_dim) action sequences."""
    n = config.num_policy_trajectories
    keys = jax.random.split(key, config.horizon)
    z = _repeat(z0, n)

    def step(z, k):
        a = _policy_batch(model, z, k, n)
        return jax.vmap(model.dynamics)(z, a), a

    # H - 1 dynamics steps, then the last action from the final latent (no wasted model step).
    z_last, actions = jax.lax.scan(step, z, keys[:-1], unroll=config.unroll)
    last = _policy_batch(model, z_last, keys[-1], n)
    return jnp.concatenate([actions, last[None]], axis=0)


def estimate_returns(
    config: MPPIConfig, model: PlanningModel, z0: Latent, actions: jax.Array, key: jax.Array
) -> jax.Array:
    """``G = sum_t gamma^t r(z_t, a_t) + gamma^H Q(z_H, pi(z_H))`` for actions of shape (horizon, N, act_dim)."""
    n = actions.shape[1]
    z = _repeat(z0, n)

    def step(carry, a):
        z, ret, discount = carry
        r = jax.vmap(model.reward)(z, a)
        z = jax.vmap(model.dynamics)(z, a)
        return (z, ret + discount * r, discount * config.gamma), None

    init = (z, jnp.zeros((n,), actions.dtype), jnp.ones((), actions.dtype))
    (z_h, ret, discount), _ = jax.lax.scan(step, init, actions, unroll=config.unroll)
    k_policy, k_value = jax.random.split(key)
    a_h = _policy_batch(model, z_h, k_policy, n)
    return ret + discount * jax.vmap(model.value, in_axes=(0, 0, None))(z_h, a_h, k_value)


def mppi_plan(
    config: MPPIConfig,
    model: PlanningModel,
    z0: Latent,
    prev_mean: jax.Array,
    key: jax.Array,
    *,
    explore: bool,
    first_step: jax.Array | bool,
    explore_noise: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
    """Plan from latent ``z0``; returns (action (act_dim,), new_mean (horizon, act_dim), info).

    With ``explore`` the action gets the final std (at least ``config.explore_min_std``) times a standard normal
    draw (TD-MPC2), or times ``explore_noise`` (act_dim,) when given (e.g. step t of an episode's colored noise,
    :mod:`lnnmpc.agents.exploration`).

    ``new_mean`` is the final (unshifted) MPPI mean: pass it back as ``prev_mean`` on the next step. ``info`` holds
    the final ``std`` (horizon, act_dim), ``elite_value_max`` / ``elite_value_mean``, the last iteration's
    ``elite_values`` (num_elites,) (best first) and ``elite_actions`` (horizon, num_elites, act_dim), and
    ``elite_index``.
    """
    horizon, act_dim = prev_mean.shape
    if horizon != config.horizon:
        raise ValueError(f"prev_mean has horizon {horizon}, config.horizon={config.horizon}")
    dtype = prev_mean.dtype
    n_pi = config.num_policy_trajectories
    n_gauss = config.num_samples - n_pi
    k_pi, k_iter, k_select, k_noise = jax.random.split(key, 4)

    pi_actions = policy_trajectories(config, model, z0, k_pi).astype(dtype) if n_pi else None
    mean = shift_mean(prev_mean, first_step)
    std = jnp.full((horizon, act_dim), config.max_std, dtype)
    elite_actions = jnp.zeros((horizon, config.num_elites, act_dim), dtype)
    elite_values = jnp.zeros((config.num_elites,), dtype)

    def iteration(carry, k):
        mean, std, _, _ = carry
        k_sample, k_value = jax.random.split(k)
        noise = jax.random.normal(k_sample, (horizon, n_gauss, act_dim), dtype)
        actions = jnp.clip(mean[:, None] + std[:, None] * noise, -1.0, 1.0)
        if pi_actions is not None:
            actions = jnp.concatenate([pi_actions, actions], axis=1)
        values = jnp.nan_to_num(estimate_returns(config, model, z0, actions, k_value))
        elite_values, elite_idx = jax.lax.top_k(values, config.num_elites)
        elite_actions = actions[:, elite_idx]
        score = jnp.exp(config.temperature * (elite_values - elite_values.max()))
        score = score / score.sum()
        mean = jnp.einsum("e,hea->ha", score, elite_actions)
        var = jnp.einsum("e,hea->ha", score, jnp.square(elite_actions - mean[:, None]))
        std = jnp.clip(jnp.sqrt(var), config.min_std, config.max_std)
        return (mean, std, elite_actions, elite_values), None

    carry = (mean, std, elite_actions, elite_values)
    (mean, std, elite_actions, elite_values), _ = jax.lax.scan(
        iteration, carry, jax.random.split(k_iter, config.iterations), unroll=config.unroll
    )

    # Draw one elite with probability proportional to exp(temperature * (G - max G)).
    logits = config.temperature * (elite_values - elite_values.max())
    idx = jax.random.categorical(k_select, logits)
    action = elite_actions[0, idx]
    if explore:
        noise = jax.random.normal(k_noise, (act_dim,), dtype) if explore_noise is None else explore_noise
        action = action + jnp.maximum(std[0], config.explore_min_std).astype(dtype) * noise.astype(dtype)
    action = jnp.clip(action, -1.0, 1.0)
    info = {
        "std": std,
        "elite_value_max": elite_values.max(),
        "elite_value_mean": elite_values.mean(),
        "elite_values": elite_values,
        "elite_actions": elite_actions,
        "elite_index": idx,
    }
    return action, mean, info
