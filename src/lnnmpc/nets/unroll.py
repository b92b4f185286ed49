"""Sequence unroll of a liquid cell with ``jax.lax.scan``: irregular time steps, episode resets, remat.

Everything is time-major: ``inputs`` (T, B, I), ``dts`` (T, B, 1) / (T, B) / (T,) / scalar / None (= 1.0),
``resets`` (T, B) booleans. A reset at step t replaces the incoming state of the samples that have it by
``reset_state`` (zeros unless given) *before* step t is processed, so an episode boundary inside a sequence
behaves exactly like starting a fresh unroll at t.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from lnnmpc.nets.cfc import CfCCell
from lnnmpc.nets.cfc_fused import cfc_fused_unroll
from lnnmpc.nets.ltc import LTCCell, ltc_integrate, ltc_sensory_drive


class UnrollResult(NamedTuple):
    """Outputs of :func:`unroll`: ``states`` (T, B, H) after each step; ``outputs`` (T, B, O) per step."""

    states: jax.Array
    outputs: jax.Array


def time_deltas_for_sequence(dts: Any, length: int, batch_size: int, dtype: Any) -> jax.Array:
    """Broadcast per-step time deltas to (T, B, 1). Accepts None (1.0), scalar, (T,), (T, B) or (T, B, 1)."""
    if dts is None:
        dts = 1.0
    dts = jnp.asarray(dts, dtype=dtype)
    if dts.ndim == 0:
        return jnp.broadcast_to(dts, (length, batch_size, 1))
    if dts.shape == (length,):
        return jnp.broadcast_to(dts[:, None, None], (length, batch_size, 1))
    if dts.shape in ((length, batch_size), (length, batch_size, 1)):
        return dts.reshape(length, batch_size, 1)
    raise ValueError(f"time deltas of shape {dts.shape} do not match a sequence of length {length} and batch "
                     f"{batch_size}; expected a scalar, ({length},), ({length}, {batch_size}) or "
                     f"({length}, {batch_size}, 1)")


def _full_reset_state(reset_state: Any, initial_state: jax.Array) -> jax.Array:
    """``reset_state`` (None = zeros) broadcast to the (B, H) shape and dtype of ``initial_state``."""
    if reset_state is None:
        return jnp.zeros_like(initial_state)
    return jnp.broadcast_to(jnp.asarray(reset_state, initial_state.dtype), initial_state.shape)


def _checked_resets(resets: Any, length: int, batch_size: int) -> jax.Array:
    """Reset flags as a (T, B) bool array (None = no resets); ``ValueError`` on another shape."""
    shape = (length, batch_size)
    resets = jnp.zeros(shape, dtype=bool) if resets is None else jnp.asarray(resets, dtype=bool)
    if resets.shape != shape:
        raise ValueError(f"resets of shape {resets.shape} do not match the sequence's (T, B) = {shape}")
    return resets


def scan_steps(
    step: Callable[[jax.Array, Any, jax.Array], tuple[jax.Array, jax.Array]],
    initial_state: jax.Array,
    inputs: Any,
    dts: jax.Array,
    resets: jax.Array | None = None,
    *,
    reset_state: jax.Array | None = None,
    remat: bool = False,
    scan_unroll: int = 1,
) -> UnrollResult:
    """Scan ``step(state (B, H), x, dt (B, 1)) -> (state, output)`` over time.

    ``inputs`` is an array (T, B, I) or any pytree scanned along its leading (time) axis; ``dts`` (T, B, 1)
    (already shaped); ``resets`` (T, B) or None; ``reset_state`` broadcastable to (B, H) (default zeros). With
    ``remat`` each step is wrapped in ``jax.checkpoint``, so the backward pass stores only the (B, H) carries
    and recomputes a step's intermediates when it needs them (an LTC with ``recompute_synapses=False``
    otherwise keeps several B * H^2 tensors per sub-step).
    ``scan_unroll`` is passed to ``jax.lax.scan(unroll=...)`` (steps per loop iteration; a speed knob only).
    """
    reset_state = _full_reset_state(reset_state, initial_state)
    resets = _checked_resets(resets, dts.shape[0], initial_state.shape[0])
    body_step = jax.checkpoint(step) if remat else step

    def body(state, per_step):
        x, dt, reset = per_step
        state = jnp.where(reset[:, None], reset_state, state)
        new_state, output = body_step(state, x, dt)
        return new_state, (new_state, output)

    _, (states, outputs) = jax.lax.scan(body, initial_state, (inputs, dts, resets), unroll=scan_unroll)
    return UnrollResult(states, outputs)


def unroll(
    cell: nn.Module,
    variables: Any,
    initial_state: jax.Array,
    inputs: jax.Array,
    dts: Any = None,
    resets: jax.Array | None = None,
    *,
    reset_state: jax.Array | None = None,
    remat: bool = False,
    dropout_rng: jax.Array | None = None,
    scan_unroll: int = 1,
    fused: bool = True,
) -> UnrollResult:
    """Run ``cell`` (a :class:`CfCCell` or :class:`LTCCell`) with ``variables`` over a time-major sequence.

    Args:
        cell: the cell module (its config; parameters come from ``variables``).
        variables: ``{'params': ...}`` as returned by ``cell.init`` or :func:`load_ncps_state_dict`.
        initial_state: (B, H) state before the first step.
        inputs: (T, B, I).
        dts: elapsed time per step: None (1.0), scalar, (T,), (T, B) or (T, B, 1).
        resets: optional (T, B) booleans; True restarts that sample from ``reset_state`` before the step.
        reset_state: state after a reset, broadcastable to (B, H); zeros by default.
        remat: rematerialise each step in the backward pass (``jax.checkpoint``).
        dropout_rng: enables CfC backbone dropout (training mode) with a fresh key per step.
        scan_unroll: time steps per ``lax.scan`` loop iteration (same results; may be faster on GPU).
        fused: use the sequence-level fast paths (same values up to float32 round-off): a CfC without dropout
            runs :func:`~lnnmpc.nets.cfc_fused.cfc_fused_unroll` (``remat`` does not apply: it stores only
            (T, B, U) residuals); an LTC computes its sensory currents for all steps before
            the scan. ``False`` scans ``cell.apply`` step by step.

    Returns:
        ``UnrollResult(states (T, B, H), outputs (T, B, O))``; ``states[-1]`` is the final state.
    Works under ``jax.vmap`` over stacked ``variables`` (one parameter set per seed) and under ``jax.jit``.
    """
    length, batch_size = inputs.shape[:2]
    dts = time_deltas_for_sequence(dts, length, batch_size, jnp.result_type(inputs, initial_state))
    options = {"reset_state": reset_state, "remat": remat, "scan_unroll": scan_unroll}
    if fused and dropout_rng is None and isinstance(cell, CfCCell):
        resets = _checked_resets(resets, length, batch_size)
        reset_state = _full_reset_state(reset_state, initial_state)
        states = cfc_fused_unroll(cell, variables["params"], initial_state, inputs, dts, resets, reset_state,
                                  scan_unroll)
        return UnrollResult(states, states)
    if fused and isinstance(cell, LTCCell):
        params = variables["params"]
        drive, conductance = ltc_sensory_drive(cell, params, inputs)

        def ltc_step(state, drive_and_conductance, dt):
            return ltc_integrate(cell, params, state, *drive_and_conductance, dt)

        return scan_steps(ltc_step, initial_state, (drive, conductance), dts, resets, **options)
    if dropout_rng is None:
        def step(state, x, dt):
            return cell.apply(variables, state, x, dt)

        return scan_steps(step, initial_state, inputs, dts, resets, **options)

    def step_with_dropout(state, x_and_key, dt):
        x, key = x_and_key
        return cell.apply(variables, state, x, dt, deterministic=False, rngs={"dropout": key})

    keyed_inputs = (inputs, jax.random.split(dropout_rng, length))
    return scan_steps(step_with_dropout, initial_state, keyed_inputs, dts, resets, **options)
