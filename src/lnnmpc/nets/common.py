"""Helpers shared by the liquid cells: config checks, time-delta shaping, torch-style initialisers."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import jax
import jax.numpy as jnp


def check_choice(name: str, value: Any, allowed: Iterable[Any]) -> None:
    """Raise ``ValueError`` naming ``value`` and the allowed values unless ``value`` is one of them."""
    allowed = tuple(allowed)
    if value not in allowed:
        raise ValueError(f"{name}={value!r} is not supported; allowed values: {list(allowed)}")


def check_int_at_least(name: str, value: Any, minimum: int) -> None:
    """Raise ``ValueError`` unless ``value`` is an integer ``>= minimum`` (bools are rejected)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name}={value!r} is invalid; expected an integer >= {minimum}")


def check_fraction(name: str, value: Any) -> None:
    """Raise ``ValueError`` unless ``0 <= value < 1`` (a dropout rate)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value < 1.0:
        raise ValueError(f"{name}={value!r} is invalid; expected a number in [0, 1)")


def check_non_negative(name: str, value: Any) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number ``>= 0``."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value < float("inf"):
        raise ValueError(f"{name}={value!r} is invalid; expected a finite number >= 0")


class ZeroInitialState:
    """Mixin for cells whose recurrent state is a (B, hidden_size) array that starts at zero."""

    hidden_size: int

    @property
    def state_size(self) -> int:
        """Size H of the recurrent state."""
        return self.hidden_size

    def initial_state(self, batch_size: int, dtype: Any = jnp.float32) -> jax.Array:
        """Zero state of shape (batch_size, H), as ncps uses when ``hx`` is None."""
        return jnp.zeros((batch_size, self.hidden_size), dtype)


def as_time_delta(dt: Any, batch_size: int, dtype: Any) -> jax.Array:
    """Return the elapsed time as a ``(B, 1)`` array.

    Accepted shapes: scalar (same Δt for every sample), ``(B,)`` or ``(B, 1)`` (per-sample Δt). A ``(B,)``
    vector is reshaped to a column, never broadcast against the hidden axis (the ncps-torch wrapper bug).
    """
    dt = jnp.asarray(dt, dtype=dtype)
    if dt.ndim == 0:
        return jnp.broadcast_to(dt, (batch_size, 1))
    if dt.shape in ((batch_size,), (batch_size, 1)):
        return dt.reshape(batch_size, 1)
    raise ValueError(f"time delta of shape {dt.shape} does not match batch size {batch_size}; "
                     f"expected a scalar, ({batch_size},) or ({batch_size}, 1)")


def torch_linear_bias_init(fan_in: int):
    """Initialiser of torch ``nn.Linear`` biases: ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``."""
    bound = 1.0 / float(fan_in) ** 0.5

    def init(key: jax.Array, shape: tuple[int, ...], dtype: Any = jnp.float32) -> jax.Array:
        return jax.random.uniform(key, shape, dtype, minval=-bound, maxval=bound)

    return init


def uniform_range(minval: float, maxval: float):
    """Initialiser drawing ``U(minval, maxval)`` (ncps's ``torch.rand * (max - min) + min``)."""

    def init(key: jax.Array, shape: tuple[int, ...], dtype: Any = jnp.float32) -> jax.Array:
        return jax.random.uniform(key, shape, dtype, minval=minval, maxval=maxval)

    return init


def constant_array(value: Any):
    """Initialiser returning a fixed array (used for wiring-derived reversal potentials)."""

    def init(key: jax.Array, shape: tuple[int, ...], dtype: Any = jnp.float32) -> jax.Array:
        del key
        out = jnp.asarray(value, dtype=dtype)
        if out.shape != tuple(shape):
            raise ValueError(f"constant initialiser has shape {out.shape}, parameter needs {tuple(shape)}")
        return out

    return init
