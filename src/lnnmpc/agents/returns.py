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
    v_H). ``gamma`` and ``lambda_`` are numbers in [0, 1] (may be traced).
    """
    if rewards.shape != next_values.shape:
        raise ValueError(f"rewards {rewards.shape} and next_values {next_values.shape} must have the same shape")

    def step(following, per_step):
        reward, value = per_step
        target = reward + gamma * ((1.0 - lambda_) * value + lambda_ * following)
        return target, target

    _, targets = jax.lax.scan(step, next_values[-1], (rewards, next_values), reverse=True)
    return jnp.asarray(targets)
