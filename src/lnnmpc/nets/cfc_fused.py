"""Sequence-level CfC unroll for accelerators: hoisted input projection, one head matmul, hoisted weight grads.

Same parameters (ncps layout) and the same values as scanning :class:`~lnnmpc.nets.cfc.CfCCell` step by step,
up to float32 round-off; the work is rearranged so that a GPU runs fewer, larger kernels:

* the input part of the first layer (``x @ W_x + b`` of ``backbone_0``, or of the heads without a backbone)
  is one (T*B, I) matmul before the scan; only ``h @ W_h`` stays inside;
* the heads ``ff1, ff2, time_a, time_b`` are one (U, 4H) matmul per step instead of four;
* a custom VJP runs the backward recurrence with two matmuls per step (through the heads and through
  ``W_h``) and stores the per-step cotangents of every layer's output; all weight gradients are then single
  matmuls contracting over T*B after the scan (autodiff would accumulate them step by step inside it).

Residuals stored for the backward pass: the incoming states (T, B, H) and every layer's pre-activation
(T, B, U or nH*H), so per-step rematerialisation is never needed. Dropout is not supported here
(:func:`lnnmpc.nets.unroll.unroll` falls back to the step-by-step path when a dropout rng is given).
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp

from lnnmpc.nets.cfc import BACKBONE_ACTIVATIONS, CfCCell, cfc_head_names, cfc_update


def cfc_fused_unroll(
    cell: CfCCell, params: Any, initial_state: jax.Array, inputs: jax.Array, dts: jax.Array,
    resets: jax.Array, reset_state: jax.Array, scan_unroll: int = 1,
) -> jax.Array:
    """States (T, B, H) of ``cell`` with ``params`` (the ``'params'`` collection) over a sequence.

    ``initial_state`` (B, H); ``inputs`` (T, B, I); ``dts`` (T, B, 1); ``resets`` (T, B) booleans (the state
    is replaced by ``reset_state`` (B, H) before a flagged step); ``scan_unroll`` as in ``jax.lax.scan``.
    """
    hidden = cell.hidden_size
    first_name = "backbone_0" if cell.backbone_layers > 0 else None
    heads = cfc_head_names(cell.mode)
    head_kernel = jnp.concatenate([params[name]["kernel"] for name in heads], axis=1)
    head_bias = jnp.concatenate([params[name]["bias"] for name in heads], axis=0)
    if first_name is None:
        first_kernel, first_bias, rest = head_kernel, head_bias, []
    else:
        first_kernel, first_bias = params[first_name]["kernel"], params[first_name]["bias"]
        rest = [(params[f"backbone_{k}"]["kernel"], params[f"backbone_{k}"]["bias"])
                for k in range(1, cell.backbone_layers)] + [(head_kernel, head_bias)]
    n_inputs = first_kernel.shape[0] - hidden
    x_projection = jnp.einsum("tbi,if->tbf", inputs, first_kernel[:n_inputs]) + first_bias
    extra = (params["w_tau"], params["A"]) if cell.mode == "pure" else ()
    reset_mask = resets.astype(initial_state.dtype)[:, :, None]
    config = (cell.mode, cell.backbone_activation, len(heads), scan_unroll)
    weights = (first_kernel[n_inputs:], tuple(rest), extra)
    return _scan(config, weights, initial_state, x_projection, dts, reset_mask, reset_state)


def _step(config, weights, state, x_projection, dt):
    """One step from the pre-reset ``state`` (B, H); returns the new state and the dense-layer outputs."""
    mode, activation, n_heads, _ = config
    recurrent_kernel, rest, extra = weights
    act = BACKBONE_ACTIVATIONS[activation]
    outputs = [x_projection + state @ recurrent_kernel]
    for kernel, bias in rest:
        outputs.append(act(outputs[-1]) @ kernel + bias)
    new_state = cfc_update(mode, tuple(jnp.split(outputs[-1], n_heads, axis=-1)), dt, extra)
    return new_state, outputs


@partial(jax.custom_vjp, nondiff_argnums=(0,))
def _scan(config, weights, initial_state, x_projection, dts, reset_mask, reset_state):
    return _forward(config, weights, initial_state, x_projection, dts, reset_mask, reset_state, False)


def _forward(config, weights, initial_state, x_projection, dts, reset_mask, reset_state, keep_residuals=True):
    """Scan the steps; returns the states (T, B, H), plus the residuals when ``keep_residuals``."""
    def body(state, per_step):
        x_proj, dt, reset = per_step
        state = jnp.where(reset > 0, reset_state, state)
        new_state, outputs = _step(config, weights, state, x_proj, dt)
        return new_state, ((new_state, state, outputs) if keep_residuals else new_state)

    _, per_step = jax.lax.scan(body, initial_state, (x_projection, dts, reset_mask), unroll=config[3])
    return per_step


def _scan_fwd(config, weights, initial_state, x_projection, dts, reset_mask, reset_state):
    states, incoming, outputs = _forward(config, weights, initial_state, x_projection, dts, reset_mask,
                                         reset_state)
    return states, (weights, incoming, outputs, dts, reset_mask)


def _scan_bwd(config, residuals, state_cotangents):
    mode, activation, n_heads, scan_unroll = config
    weights, incoming, outputs, dts, reset_mask = residuals
    recurrent_kernel, rest, extra = weights
    act = BACKBONE_ACTIVATIONS[activation]

    def body(carry, per_step):
        cotangent, layer_outputs, dt, reset = per_step
        cotangent = cotangent + carry
        heads = layer_outputs[-1]
        _, update_vjp = jax.vjp(lambda h, d, e: cfc_update(mode, tuple(jnp.split(h, n_heads, axis=-1)), d, e),
                                heads, dt, extra)
        d_heads, d_dt, d_extra = update_vjp(cotangent)
        d_outputs = [d_heads]
        for (kernel, _), pre in zip(reversed(rest), reversed(layer_outputs[:-1]), strict=True):
            _, act_vjp = jax.vjp(act, pre)
            d_outputs.append(act_vjp(d_outputs[-1] @ kernel.T)[0])
        d_state = d_outputs[-1] @ recurrent_kernel.T
        d_reset_state = jnp.where(reset > 0, d_state, 0.0)
        carry = jnp.where(reset > 0, 0.0, d_state)
        return carry, (d_outputs[::-1], d_dt, d_extra, d_reset_state)

    d_initial, (d_outputs, d_dts, d_extra, d_reset_state) = jax.lax.scan(
        body, jnp.zeros_like(state_cotangents[0]), (state_cotangents, outputs, dts, reset_mask), reverse=True,
        unroll=scan_unroll)
    d_recurrent = jnp.einsum("tbh,tbf->hf", incoming, d_outputs[0])
    d_rest = tuple((jnp.einsum("tbu,tbf->uf", act(pre), d_out), jnp.sum(d_out, axis=(0, 1)))
                   for pre, d_out in zip(outputs[:-1], d_outputs[1:], strict=True))
    d_extra = jax.tree.map(lambda g: jnp.sum(g, axis=0), d_extra)
    d_weights = (d_recurrent, d_rest, d_extra)
    return (d_weights, d_initial, d_outputs[0], d_dts, jnp.zeros_like(reset_mask),
            jnp.sum(d_reset_state, axis=0))


_scan.defvjp(_scan_fwd, _scan_bwd)
