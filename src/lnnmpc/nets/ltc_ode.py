"""LTC ODE solver: synaptic currents, the semi-implicit Euler sub-step and a hand-derived backward pass.

:func:`ltc_unfolds` runs ``n`` sub-steps of the recurrent LTC ODE with the same forward operations as the
autodiff path (:func:`synaptic_currents` + :func:`semi_implicit_euler_step` per sub-step), but with a
``jax.custom_vjp`` whose backward pass never materialises a (B, H, H) tensor: it stores only the (B, H)
state, numerator and conductance of every sub-step and, for the cotangents, recomputes the synaptic sigmoids
inside a few reductions (one reduction over the target axis per sub-step for the state cotangent, and one
multi-output reduction over (sub-steps, batch) per call for the four (H, H) parameter cotangents). Each
reduction is an elementwise chain over small inputs that XLA fuses into the reduce, so the backward pass
reads and writes O(B H) bytes per sub-step instead of several B H^2 intermediates.

Notation (per sub-step ``k``, index ``b`` batch, ``i`` source, ``j`` target neuron)::

    sg_bij = sigmoid(sigma_ij (v_bi - mu_ij)),   a_bij = w_ij sg_bij
    N_bj = drive_bj + sum_i a_bij erev_ij,      G_bj = conductance_bj + sum_i a_bij
    D_bj = cm_j + s_b G_bj (1 where it is 0),   v'_bj = v_bj + s_b (N_bj - v_bj G_bj) / D_bj

Given the cotangent ``g`` of ``v'``: ``dN = g s / D``, ``dD = -g s (N - v G) / D^2`` (0 where D was
replaced), ``dG = -dN v + dD s``, ``ds = sum_j g (N - v G) / D + dD G``, ``dcm = sum_b dD``; with
``da_bij = dN_bj erev_ij + dG_bj``: ``dv_bi = g_bi - dN_bi G_bi + sum_j da_bij w_ij sg_bij (1 - sg_bij)
sigma_ij``, ``dw = sum_b sg da``, ``derev = w sum_b sg dN``, ``dsigma = w sum_b da sg (1 - sg) (v - mu)``,
``dmu = -sigma w sum_b da sg (1 - sg)``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp


def synaptic_currents(
    presynaptic: jax.Array, weight: jax.Array, sigma: jax.Array, mu: jax.Array, erev: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Summed synaptic drive and conductance onto each target neuron.

    ``presynaptic`` (..., B, N); ``weight, sigma, mu, erev`` (N, H). Activation
    ``a = weight * sigmoid(sigma * (presynaptic[..., :, None] - mu))`` (..., B, N, H); returns
    ``(sum_N a * erev, sum_N a)``, both (..., B, H).
    """
    activation = weight * jax.nn.sigmoid(sigma * (presynaptic[..., :, None] - mu))
    return jnp.sum(activation * erev, axis=-2), jnp.sum(activation, axis=-2)


def semi_implicit_euler_step(
    v: jax.Array, cm: jax.Array, drive: jax.Array, conductance: jax.Array, sub_step: jax.Array
) -> jax.Array:
    """One fused Euler sub-step ``v + s (drive - v G) / (cm + s G)``; exactly ``v`` when ``s = 0``.

    ``v, drive, conductance`` (B, H); ``cm`` (H,); ``sub_step`` (B, 1). A zero denominator (only possible with
    ``cm = 0`` and ``s = 0``) is replaced by 1 so that the update is 0 instead of NaN.
    """
    denominator = cm + sub_step * conductance
    denominator = jnp.where(denominator == 0, jnp.ones_like(denominator), denominator)
    return v + sub_step * (drive - v * conductance) / denominator


def _forward(n_unfolds, v, drive, conductance, cm, w, sigma, mu, erev, sub_step):
    """The sub-steps; returns the final state and the per-sub-step (v, N, G), each (n_unfolds, B, H)."""
    states, numerators, conductances = [], [], []
    for _ in range(n_unfolds):
        recurrent_num, recurrent_den = synaptic_currents(v, w, sigma, mu, erev)
        total_num, total_den = drive + recurrent_num, conductance + recurrent_den
        states.append(v)
        numerators.append(total_num)
        conductances.append(total_den)
        v = semi_implicit_euler_step(v, cm, total_num, total_den, sub_step)
    return v, (jnp.stack(states), jnp.stack(numerators), jnp.stack(conductances))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def ltc_unfolds(
    n_unfolds: int,
    v: jax.Array,
    drive: jax.Array,
    conductance: jax.Array,
    cm: jax.Array,
    w: jax.Array,
    sigma: jax.Array,
    mu: jax.Array,
    erev: jax.Array,
    sub_step: jax.Array,
) -> jax.Array:
    """``n_unfolds`` semi-implicit Euler sub-steps of the recurrent LTC ODE, with a fused backward pass.

    ``v, drive, conductance`` (B, H) (``drive``/``conductance`` as from ``ltc_sensory_drive``: leak plus
    sensory terms, epsilon included); ``cm`` (H,) and ``w`` (H, H) already made positive; ``sigma, mu,
    erev`` (H, H) indexed [source, target]; ``sub_step`` (B, 1). Returns the new state (B, H), with the
    same forward operations as the autodiff path. Differentiable in every array argument (first order via
    the hand-derived rule; the rule itself is plain JAX, so higher orders work too).
    """
    return _forward(n_unfolds, v, drive, conductance, cm, w, sigma, mu, erev, sub_step)[0]


def _ltc_unfolds_fwd(n_unfolds, v, drive, conductance, cm, w, sigma, mu, erev, sub_step):
    new_v, per_sub_step = _forward(n_unfolds, v, drive, conductance, cm, w, sigma, mu, erev, sub_step)
    return new_v, (per_sub_step, cm, w, sigma, mu, erev, sub_step)


def _ltc_unfolds_bwd(n_unfolds, residuals, g):
    (states, numerators, conductances), cm, w, sigma, mu, erev, sub_step = residuals
    dnum, dcond, dden_total, dsub_step = [], [], jnp.zeros_like(g), jnp.zeros_like(sub_step)
    # Sequential part: the state cotangent through every sub-step, last to first.
    for k in reversed(range(n_unfolds)):
        v, total_num, total_den = states[k], numerators[k], conductances[k]
        denominator = cm + sub_step * total_den
        replaced = denominator == 0
        denominator = jnp.where(replaced, jnp.ones_like(denominator), denominator)
        residual = total_num - v * total_den
        d_num = g * sub_step / denominator
        d_den = jnp.where(replaced, jnp.zeros_like(g), -g * sub_step * residual / (denominator * denominator))
        d_cond = d_den * sub_step - d_num * v
        dsub_step = dsub_step + jnp.sum(g * residual / denominator + d_den * total_den, axis=-1, keepdims=True)
        dden_total = dden_total + d_den
        sg = jax.nn.sigmoid(sigma * (v[:, :, None] - mu))
        d_activation = d_num[:, None, :] * erev + d_cond[:, None, :]
        g = g - d_num * total_den + jnp.sum(d_activation * (w * sigma) * (sg * (1 - sg)), axis=-1)
        dnum.append(d_num)
        dcond.append(d_cond)
    dnum, dcond = jnp.stack(dnum[::-1]), jnp.stack(dcond[::-1])
    # Parameter cotangents: one (sub-step, batch) reduction each over recomputed sigmoids.
    sg = jax.nn.sigmoid(sigma * (states[..., :, None] - mu))
    d_activation = dnum[..., None, :] * erev + dcond[..., None, :]
    d_pre = d_activation * (sg * (1 - sg))
    axes = (0, 1)
    dw = jnp.sum(sg * d_activation, axis=axes)
    derev = w * jnp.sum(sg * dnum[..., None, :], axis=axes)
    dsigma = w * jnp.sum(d_pre * (states[..., :, None] - mu), axis=axes)
    dmu = -(sigma * w) * jnp.sum(d_pre, axis=axes)
    dcm = jnp.sum(dden_total, axis=0).reshape(cm.shape)
    return g, jnp.sum(dnum, axis=0), jnp.sum(dcond, axis=0), dcm, dw, dsigma, dmu, derev, dsub_step


ltc_unfolds.defvjp(_ltc_unfolds_fwd, _ltc_unfolds_bwd)
