"""Observation corruptions that turn the MDPs into POMDPs (SPEC §3), as pure jittable functions.

Pipeline, applied to the clean observation captured at every agent step t:

1. ``remove_vel``: drop dm_control's ``velocity`` key (a static index selection).
2. ``obs_noise=σ``: add N(0, σ²) to every remaining dimension.
3. ``flicker=s``: at reset draw p_i = min(|N(0, s²)|, 1) per dimension; each step zero dimension i with
   probability p_i (after the noise).
4. ``delay=N``: the corrupted observations are captured into a ring buffer of N + 1 slots; each step draws
   d_t ~ U{0..N} and delivers the observation captured at τ_t = max(τ_{t-1}, t - d_t), so observations arrive in
   order and are at most N agent steps old. The agent also receives Δt_t = τ_t - τ_{t-1} >= 0 (agent steps);
   Σ_{k<=t} Δt_k = τ_t. Without delay Δt_t = 1. At reset τ_0 = 0 and Δt_0 = 1 (the first observation of an
   episode carries the nominal step; recurrent encoders restart their state there anyway).

All state lives in :class:`CorruptionState` inside the environment state, and every random draw comes from the
environment state's key, so corruptions are reproducible for a fixed key and independent across keys.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

OPTIONS = ("remove_vel", "obs_noise", "flicker", "delay")


@dataclasses.dataclass(frozen=True)
class CorruptionConfig:
    """Validated corruption settings (all off by default)."""

    remove_vel: bool = False
    obs_noise: float = 0.0
    flicker: float = 0.0
    delay: int = 0

    def __post_init__(self):
        if not isinstance(self.remove_vel, bool | np.bool_):
            raise ValueError(f"remove_vel must be True or False, got {self.remove_vel!r}")
        for name in ("obs_noise", "flicker"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
            if value < 0:
                raise ValueError(f"{name} must be >= 0 (a standard deviation), got {value!r}")
        if isinstance(self.delay, bool) or not isinstance(self.delay, int | np.integer) or self.delay < 0:
            raise ValueError(f"delay must be an integer number of agent steps >= 0, got {self.delay!r}")

    @classmethod
    def from_options(cls, options: dict) -> CorruptionConfig:
        unknown = sorted(set(options) - set(OPTIONS))
        if unknown:
            raise ValueError(f"unknown observation option(s) {unknown}; known: {', '.join(OPTIONS)}")
        return cls(**options)


@struct.dataclass
class CorruptionState:
    """Per-episode corruption state.

    Attributes:
      flicker_p: (obs_dim,) per-dimension drop probabilities (zeros without flicker).
      buffer: (delay + 1, obs_dim) ring buffer of captured (noisy, flickered) observations.
      tau: () int32, capture step of the last delivered observation.
    """

    flicker_p: jax.Array
    buffer: jax.Array
    tau: jax.Array


def kept_indices(obs_keys: tuple[tuple[str, int], ...], config: CorruptionConfig) -> np.ndarray:
    """Indices of the clean observation the agent sees (static)."""
    indices, start = [], 0
    for key, size in obs_keys:
        if not (config.remove_vel and key == "velocity"):
            indices.extend(range(start, start + size))
        start += size
    return np.asarray(indices, dtype=np.int32)


def _capture(config: CorruptionConfig, flicker_p: jax.Array, key: jax.Array, obs: jax.Array) -> jax.Array:
    """Noise then flicker on one observation (obs_dim,)."""
    k_noise, k_flicker = jax.random.split(key)
    if config.obs_noise > 0:
        obs = obs + config.obs_noise * jax.random.normal(k_noise, obs.shape, obs.dtype)
    if config.flicker > 0:
        dropped = jax.random.uniform(k_flicker, obs.shape) < flicker_p
        obs = jnp.where(dropped, jnp.zeros_like(obs), obs)
    return obs


def corruption_reset(
    config: CorruptionConfig, key: jax.Array, obs: jax.Array
) -> tuple[CorruptionState, jax.Array, jax.Array]:
    """Starts an episode from the first kept observation (obs_dim,).

    Returns:
      (state, delivered observation (obs_dim,), Δt () = 1).
    """
    k_p, k_capture = jax.random.split(key)
    flicker_p = jnp.minimum(jnp.abs(config.flicker * jax.random.normal(k_p, obs.shape, obs.dtype)), 1.0)
    captured = _capture(config, flicker_p, k_capture, obs)
    buffer = jnp.broadcast_to(captured, (config.delay + 1, *obs.shape))
    state = CorruptionState(flicker_p=flicker_p, buffer=buffer, tau=jnp.zeros((), jnp.int32))
    return state, captured, jnp.ones((), obs.dtype)


def corruption_step(
    config: CorruptionConfig, state: CorruptionState, key: jax.Array, t: jax.Array, obs: jax.Array
) -> tuple[CorruptionState, jax.Array, jax.Array]:
    """Captures the kept observation of agent step ``t`` (>= 1) and delivers one.

    Args:
      t: () int32 agent step index of ``obs`` within the episode.
      obs: (obs_dim,) clean kept observation at step t.

    Returns:
      (state, delivered observation (obs_dim,), Δt ()).
    """
    k_capture, k_delay = jax.random.split(key)
    captured = _capture(config, state.flicker_p, k_capture, obs)
    if config.delay == 0:
        return state.replace(tau=t), captured, jnp.ones((), obs.dtype)
    slots = config.delay + 1
    buffer = state.buffer.at[t % slots].set(captured)
    lag = jax.random.randint(k_delay, (), 0, config.delay + 1)
    tau = jnp.maximum(state.tau, t - lag).astype(jnp.int32)
    delivered = buffer[tau % slots]
    dt = (tau - state.tau).astype(obs.dtype)
    return state.replace(buffer=buffer, tau=tau), delivered, dt
