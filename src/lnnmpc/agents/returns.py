"""TD(λ) value targets over a sampled sequence, computed backwards with ``lax.scan`` (SPEC §4, thesis eq. 4.17).

    R_t = r_t + γ ((1 − λ) v_{t+1} + λ R_{t+1}),   R_H = v_H,

for t = H−1 … 0, where ``v_{t+1} = Q̄(z_{t+1}, π(z_{t+1}))`` is the bootstrap value of the next latent. So the
last target is the one-step target ``r_{H−1} + γ v_H``; λ = 0 gives one-step TD targets everywhere and λ = 1 the
discounted sum of the remaining rewards plus ``γ^{H−t} v_H``. The sampled windows never cross an episode and
the tasks only truncate, so there is no termination mask.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def lambda_returns(rewards: jax.Array, next_values: jax.Array, gamma: float, lambda_: float) -> jax.Array:
    """TD(λ) targets (H, ...) from ``rewards`` r_0..r_{H−1} and ``next_values`` v_1..v_H, both (H, ...).

    ``next_values[t]`` is the value of the latent after step t (``next_values[-1]`` is the final bootstrap
    v_H). ``gamma`` and ``lambda_`` are numbers in [0, 1] (may be traced). A ``lambda_`` of exactly 0 given as a
    Python number gives one-step targets r_t + γ v_{t+1} directly, without the backward scan (H sequential steps
    fewer in every update; the same numbers).
    """
    if rewards.shape != next_values.shape:
        raise ValueError(f"rewards {rewards.shape} and next_values {next_values.shape} must have the same shape")
    if isinstance(lambda_, (int, float)) and lambda_ == 0:
        return rewards + gamma * next_values

    def step(following, per_step):
        reward, value = per_step
        target = reward + gamma * ((1.0 - lambda_) * value + lambda_ * following)
        return target, target

    _, targets = jax.lax.scan(step, next_values[-1], (rewards, next_values), reverse=True)
    return jnp.asarray(targets)
