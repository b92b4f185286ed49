"""dm_control's `rewards.tolerance` in jax.numpy.

Same semantics as `dm_control.utils.rewards.tolerance` for the sigmoids the suite tasks use
(gaussian, linear, quadratic); works elementwise on arrays of any shape and under `jit`/`vmap`.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

SIGMOIDS = ("gaussian", "linear", "quadratic")


def _sigmoid(x: jnp.ndarray, value_at_margin: float, sigmoid: str) -> jnp.ndarray:
    """Maps distance-in-margins `x >= 0` to (0, 1], equal to `value_at_margin` at `x == 1`."""
    if sigmoid == "gaussian":
        scale = math.sqrt(-2.0 * math.log(value_at_margin))
        return jnp.exp(-0.5 * (x * scale) ** 2)
    if sigmoid == "linear":
        scaled = x * (1.0 - value_at_margin)
        return jnp.where(jnp.abs(scaled) < 1.0, 1.0 - scaled, 0.0)
    if sigmoid == "quadratic":
        scaled = x * math.sqrt(1.0 - value_at_margin)
        return jnp.where(jnp.abs(scaled) < 1.0, 1.0 - scaled**2, 0.0)
    raise ValueError(f"unknown sigmoid {sigmoid!r}; known: {', '.join(SIGMOIDS)}")


def tolerance(
    x: jnp.ndarray,
    bounds: tuple[float, float] = (0.0, 0.0),
    margin: float = 0.0,
    sigmoid: str = "gaussian",
    value_at_margin: float = 0.1,
) -> jnp.ndarray:
    """1 inside `bounds`, decaying with distance outside them (shape of `x`).

    Args:
      x: values, any shape.
      bounds: (lower, upper), either may be infinite.
      margin: distance over which the reward falls to `value_at_margin`; 0 gives a step function.
      sigmoid: "gaussian", "linear" or "quadratic".
      value_at_margin: reward at distance `margin` from the bounds.
    """
    lower, upper = bounds
    if lower > upper:
        raise ValueError(f"lower bound {lower} exceeds upper bound {upper}")
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    in_bounds = jnp.logical_and(lower <= x, x <= upper)
    if margin == 0:
        return jnp.where(in_bounds, 1.0, 0.0).astype(jnp.result_type(x, float))
    distance = jnp.where(x < lower, lower - x, x - upper) / margin
    return jnp.where(in_bounds, 1.0, _sigmoid(distance, value_at_margin, sigmoid))
