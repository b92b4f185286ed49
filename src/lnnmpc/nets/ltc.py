"""Liquid time-constant (LTC) cell, ncps-torch semantics (``ncps.torch.LTCCell``, ``FullyConnected`` wiring).

Per input step the conductance-based ODE ``cm dv/dt = gleak (vleak - v) + sum_j a_j (erev_j - v)`` is
integrated with ``ode_unfolds`` semi-implicit ("hybrid") Euler sub-steps of size ``s = dt / ode_unfolds``,
where the synaptic activations are ``a = pos(w) * sigmoid(sigma * (v_src - mu))`` (recurrent) and the same
form on the mapped input (sensory). ncps writes one sub-step as
``v <- (cm/s * v + N) / (cm/s + D + eps)``; this module evaluates the algebraically equal form
``v <- v + s * (N - v * D') / (cm + s * D')`` with ``D' = D + eps``, in which ``dt`` multiplies instead of
divides: ``dt = 0`` is well defined and leaves the state exactly unchanged.

``pos`` is softplus when ``implicit_param_constraints`` (the default of the ncps ``LTC`` wrapper), identity
otherwise (then keep ``w, sensory_w, cm, gleak >= 0`` yourself, e.g. with :func:`clip_ltc_parameters`
after each optimiser step, as ncps's ``apply_weight_constraints`` does).
"""

from __future__ import annotations

import functools
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.nets.common import (
    ZeroInitialState,
    as_time_delta,
    check_choice,
    check_int_at_least,
    check_non_negative,
    constant_array,
    uniform_range,
)
from lnnmpc.nets.ltc_ode import ltc_unfolds, semi_implicit_euler_step, synaptic_currents

LTC_MAPPINGS = ("affine", "linear", "none")

# ncps LTCCell._init_ranges
LTC_INIT_RANGES = {
    "gleak": (0.001, 1.0),
    "vleak": (-0.2, 0.2),
    "cm": (0.4, 0.6),
    "w": (0.001, 1.0),
    "sigma": (3.0, 8.0),
    "mu": (0.3, 0.8),
    "sensory_w": (0.001, 1.0),
    "sensory_sigma": (3.0, 8.0),
    "sensory_mu": (0.3, 0.8),
}

CONSTRAINED_PARAMETERS = ("gleak", "cm", "w", "sensory_w")


@functools.lru_cache(maxsize=32)
def fully_connected_polarities(hidden_size: int, input_size: int, seed: int = 1111) -> tuple[np.ndarray, ...]:
    """Reversal-potential signs of ncps's ``FullyConnected`` wiring (self connections on).

    Reproduces ncps's draw order: ``numpy.random.default_rng(seed).choice([-1, 1, 1])`` once per recurrent
    synapse (source-major), then once per sensory synapse. Returns ``(erev (H, H), sensory_erev (S, H))``
    (cached and read-only: Flax re-evaluates initialisers to check shapes).
    """
    rng = np.random.default_rng(seed)
    choices = [-1, 1, 1]
    recurrent = np.array([rng.choice(choices) for _ in range(hidden_size * hidden_size)], dtype=np.float32)
    sensory = np.array([rng.choice(choices) for _ in range(input_size * hidden_size)], dtype=np.float32)
    recurrent, sensory = recurrent.reshape(hidden_size, hidden_size), sensory.reshape(input_size, hidden_size)
    recurrent.flags.writeable = sensory.flags.writeable = False
    return recurrent, sensory


def clip_ltc_parameters(variables: Any) -> Any:
    """ReLU-clip ``w, sensory_w, cm, gleak`` (ncps ``apply_weight_constraints``; for explicit constraints)."""
    params = dict(variables["params"])
    for name in CONSTRAINED_PARAMETERS:
        params[name] = jnp.maximum(params[name], 0)
    return {**variables, "params": params}


class LTCCell(ZeroInitialState, nn.Module):
    """LTC cell, fully connected. Call: ``cell.apply(variables, v, x, dt) -> (v_new, output)``.

    Shapes: ``v`` (B, H) with ``H = hidden_size``; ``x`` (B, S); ``dt`` scalar, (B,) or (B, 1) (reshaped to
    (B, 1)); ``v_new`` (B, H); ``output`` (B, M) = affine map of the first ``M = output_size`` neurons.
    Parameters: ``gleak, vleak, cm`` (H); ``w, sigma, mu, erev`` (H, H) indexed [source, target];
    ``sensory_w, sensory_sigma, sensory_mu, sensory_erev`` (S, H); ``input_w, input_b`` (S);
    ``output_w, output_b`` (M). The reversal potentials start at ncps's ``FullyConnected`` signs.

    Attributes:
        hidden_size: number of neurons H (>= 1).
        output_size: number of motor neurons M read out (1..H); ``None`` means H.
        ode_unfolds: Euler sub-steps per input step (>= 1).
        epsilon: added to the denominator (>= 0), as in ncps.
        input_mapping / output_mapping: ``"affine"`` (w * x + b), ``"linear"`` (w * x) or ``"none"``.
        implicit_param_constraints: softplus on ``w, sensory_w, cm, gleak`` (True) or identity (False).
        erev_init_seed: seed of the ``FullyConnected`` polarity draw (ncps default 1111).
        recompute_synapses: wrap the (B, N, H) synaptic activations in ``jax.checkpoint`` so the backward
            pass recomputes them from the (B, N) presynaptic values instead of storing ~5 such tensors per
            sub-step (same values; at B=256, H=64, 42 steps: 4.8 GB -> 0.25 GB and faster on CPU).
        manual_backward: run the recurrent sub-steps through :func:`~lnnmpc.nets.ltc_ode.ltc_unfolds`, whose
            hand-derived ``custom_vjp`` stores only (B, H) values per sub-step and recomputes the synaptic
            sigmoids inside fused reductions (same forward values; gradients equal up to float32 round-off).
            Takes precedence over ``recompute_synapses`` for the recurrent synapses. ``False``: JAX autodiff of
            the sub-steps (the previous path; benchmark variant ``ltc``, this one is ``ltc-vjp``).
        param_dtype: dtype of the parameters.
    """

    hidden_size: int
    output_size: int | None = None
    ode_unfolds: int = 6
    epsilon: float = 1e-8
    input_mapping: str = "affine"
    output_mapping: str = "affine"
    implicit_param_constraints: bool = True
    erev_init_seed: int = 1111
    recompute_synapses: bool = True
    manual_backward: bool = True
    param_dtype: Any = jnp.float32

    def __post_init__(self) -> None:
        check_int_at_least("hidden_size", self.hidden_size, 1)
        if self.output_size is not None:
            check_int_at_least("output_size", self.output_size, 1)
            if self.output_size > self.hidden_size:
                raise ValueError(f"output_size={self.output_size!r} is invalid; expected at most "
                                 f"hidden_size={self.hidden_size}")
        check_int_at_least("ode_unfolds", self.ode_unfolds, 1)
        check_non_negative("epsilon", self.epsilon)
        check_choice("input_mapping", self.input_mapping, LTC_MAPPINGS)
        check_choice("output_mapping", self.output_mapping, LTC_MAPPINGS)
        check_choice("implicit_param_constraints", self.implicit_param_constraints, (True, False))
        check_choice("recompute_synapses", self.recompute_synapses, (True, False))
        check_choice("manual_backward", self.manual_backward, (True, False))
        super().__post_init__()

    @property
    def readout_size(self) -> int:
        """Size M of the per-step output: the number of (motor) neurons read out."""
        return self.hidden_size if self.output_size is None else self.output_size

    def _ranged(self, name: str, shape: tuple[int, ...]) -> jax.Array:
        return self.param(name, uniform_range(*LTC_INIT_RANGES[name]), shape, self.param_dtype)

    def _mapping_params(self, prefix: str, mapping: str, size: int) -> dict[str, jax.Array]:
        params = {}
        if mapping in ("affine", "linear"):
            params[f"{prefix}_w"] = self.param(f"{prefix}_w", nn.initializers.ones, (size,), self.param_dtype)
        if mapping == "affine":
            params[f"{prefix}_b"] = self.param(f"{prefix}_b", nn.initializers.zeros, (size,), self.param_dtype)
        return params

    @nn.compact
    def __call__(self, state: jax.Array, inputs: jax.Array, dt: Any = 1.0) -> tuple[jax.Array, jax.Array]:
        """Integrate over elapsed time ``dt``; returns ``(new_state (B, H), output (B, M))``."""
        hidden, n_inputs = self.hidden_size, inputs.shape[-1]
        erev_init, sensory_erev_init = fully_connected_polarities(hidden, n_inputs, self.erev_init_seed)
        params = {name: self._ranged(name, (hidden,)) for name in ("gleak", "vleak", "cm")}
        params.update({name: self._ranged(name, (hidden, hidden)) for name in ("sigma", "mu", "w")})
        params["erev"] = self.param("erev", constant_array(erev_init), (hidden, hidden), self.param_dtype)
        params.update({name: self._ranged(name, (n_inputs, hidden))
                       for name in ("sensory_w", "sensory_sigma", "sensory_mu")})
        params["sensory_erev"] = self.param("sensory_erev", constant_array(sensory_erev_init),
                                            (n_inputs, hidden), self.param_dtype)
        params.update(self._mapping_params("input", self.input_mapping, n_inputs))
        params.update(self._mapping_params("output", self.output_mapping, self.readout_size))
        drive, conductance = ltc_sensory_drive(self, params, inputs)
        return ltc_integrate(self, params, state, drive, conductance, dt)


def _positive(cell: LTCCell, value: jax.Array) -> jax.Array:
    return jax.nn.softplus(value) if cell.implicit_param_constraints else value


def _affine(params: Any, prefix: str, values: jax.Array) -> jax.Array:
    """Elementwise input/output mapping ``w * values (+ b)`` over the last axis (absent parameters skipped)."""
    if f"{prefix}_w" in params:
        values = values * params[f"{prefix}_w"]
    if f"{prefix}_b" in params:
        values = values + params[f"{prefix}_b"]
    return values


def ltc_sensory_drive(cell: LTCCell, params: Any, inputs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Input-dependent part of the ODE: ``(gleak * vleak + sensory numerator, gleak + sensory den. + eps)``.

    ``params`` is the cell's ``'params'`` collection; ``inputs`` (..., B, S), e.g. a whole sequence (T, B, S)
    at once; returns two (..., B, H) arrays. They do not depend on the state, so :func:`lnnmpc.nets.unroll`
    computes them for all steps before the scan.
    """
    gleak = _positive(cell, params["gleak"])
    synapses = (_positive(cell, params["sensory_w"]), params["sensory_sigma"], params["sensory_mu"],
                params["sensory_erev"])
    currents = jax.checkpoint(synaptic_currents) if cell.recompute_synapses else synaptic_currents
    sensory_num, sensory_den = currents(_affine(params, "input", inputs), *synapses)
    return gleak * params["vleak"] + sensory_num, gleak + sensory_den + cell.epsilon


def ltc_integrate(
    cell: LTCCell, params: Any, state: jax.Array, drive: jax.Array, conductance: jax.Array, dt: Any
) -> tuple[jax.Array, jax.Array]:
    """The ``ode_unfolds`` Euler sub-steps from ``state`` (B, H) given :func:`ltc_sensory_drive`'s (B, H) pair.

    ``dt`` scalar, (B,) or (B, 1). Returns ``(new_state (B, H), output (B, M))``.
    """
    cm = _positive(cell, params["cm"])
    synapses = (_positive(cell, params["w"]), params["sigma"], params["mu"], params["erev"])
    sub_step = as_time_delta(dt, state.shape[0], jnp.result_type(drive, state)) / cell.ode_unfolds
    if cell.manual_backward:
        new_state = ltc_unfolds(cell.ode_unfolds, state, drive, conductance, cm, *synapses, sub_step)
        return new_state, _affine(params, "output", new_state[:, : cell.readout_size])
    currents = jax.checkpoint(synaptic_currents) if cell.recompute_synapses else synaptic_currents
    new_state = state
    for _ in range(cell.ode_unfolds):
        recurrent_num, recurrent_den = currents(new_state, *synapses)
        new_state = semi_implicit_euler_step(new_state, cm, drive + recurrent_num, conductance + recurrent_den,
                                             sub_step)
    return new_state, _affine(params, "output", new_state[:, : cell.readout_size])
