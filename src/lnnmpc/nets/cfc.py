"""Closed-form continuous-time (CfC) cell with ncps-torch semantics (``ncps.torch.CfCCell``, ncps 1.0.1).

Equations (``z`` = backbone features, ``dt`` = elapsed time of shape ``(B, 1)``)::

    z       = backbone([x ; h])                         # Linear+activation layers, [input, hidden] order
    default: h' = tanh(ff1(z)) * (1 - g) + g * tanh(ff2(z)),   g = sigmoid(time_a(z) * dt + time_b(z))
    no_gate: h' = tanh(ff1(z)) + g * tanh(ff2(z))
    pure:    h' = A - A * exp(-dt * (|w_tau| + |ff1(z)|)) * ff1(z)

The new state is also the output. Initialisation follows ncps: xavier-uniform kernels (including the pure
mode's ``(1, H)`` ``w_tau`` and ``A``) and torch's default ``U(+-1/sqrt(fan_in))`` biases. Like ncps,
backbone dropout is applied after layers 2, 3, ... only (a one-layer backbone never drops out).
"""

from __future__ import annotations

from functools import partial
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from lnnmpc.nets.common import (
    ZeroInitialState,
    as_time_delta,
    check_choice,
    check_fraction,
    check_int_at_least,
    torch_linear_bias_init,
)

CFC_MODES = ("default", "no_gate", "pure")


def lecun_tanh(x: jax.Array) -> jax.Array:
    """ncps's scaled tanh, ``1.7159 * tanh(0.666 * x)`` (0.666, not 2/3, to match ncps)."""
    return 1.7159 * jnp.tanh(0.666 * x)


BACKBONE_ACTIVATIONS = {
    "lecun_tanh": lecun_tanh,
    "silu": jax.nn.silu,
    "relu": jax.nn.relu,
    "tanh": jnp.tanh,
    "gelu": partial(jax.nn.gelu, approximate=False),  # torch nn.GELU() is the exact erf form
}


def torch_style_dense(features: int, fan_in: int, name: str, param_dtype: Any) -> nn.Dense:
    """A ``Dense`` layer initialised like torch's ``nn.Linear`` (kernel (fan_in, features) = ``W.T``)."""
    return nn.Dense(
        features,
        kernel_init=nn.initializers.xavier_uniform(),
        bias_init=torch_linear_bias_init(fan_in),
        param_dtype=param_dtype,
        name=name,
    )


class CfCCell(ZeroInitialState, nn.Module):
    """CfC cell. Call: ``cell.apply(variables, h, x, dt) -> (h_new, output)`` with ``output is h_new``.

    Shapes: ``h`` (B, H) with ``H = hidden_size``; ``x`` (B, I); ``dt`` scalar, (B,) or (B, 1) (reshaped to
    (B, 1)). Outputs (B, H). Parameters: ``backbone_{k}`` (k < backbone_layers; kernel (I+H, U) then (U, U)),
    ``ff1`` and, unless ``mode='pure'``, ``ff2``, ``time_a``, ``time_b`` (kernel (U, H), or (I+H, H) without a
    backbone); pure mode has ``w_tau`` and ``A`` of shape (1, H).

    Attributes:
        hidden_size: number of hidden units H (>= 1).
        mode: ``"default"``, ``"no_gate"`` or ``"pure"``.
        backbone_activation: ``"lecun_tanh"``, ``"silu"``, ``"relu"``, ``"tanh"`` or ``"gelu"``.
        backbone_units: width U of every backbone layer (>= 1).
        backbone_layers: number of backbone layers (>= 0; 0 feeds ``[x ; h]`` straight to the heads).
        backbone_dropout: dropout rate in [0, 1) after backbone layers 2.. (needs a ``'dropout'`` rng and
            ``deterministic=False`` to be active).
        param_dtype: dtype of the parameters.
    """

    hidden_size: int
    mode: str = "default"
    backbone_activation: str = "lecun_tanh"
    backbone_units: int = 128
    backbone_layers: int = 1
    backbone_dropout: float = 0.0
    param_dtype: Any = jnp.float32

    def __post_init__(self) -> None:
        check_int_at_least("hidden_size", self.hidden_size, 1)
        check_choice("mode", self.mode, CFC_MODES)
        check_choice("backbone_activation", self.backbone_activation, BACKBONE_ACTIVATIONS)
        check_int_at_least("backbone_units", self.backbone_units, 1)
        check_int_at_least("backbone_layers", self.backbone_layers, 0)
        check_fraction("backbone_dropout", self.backbone_dropout)
        super().__post_init__()

    @property
    def readout_size(self) -> int:
        """Size of the per-step output (the state itself for CfC)."""
        return self.hidden_size

    def _backbone(self, features: jax.Array, deterministic: bool) -> jax.Array:
        """Apply the backbone layers: (B, I+H) -> (B, U); identity when ``backbone_layers == 0``."""
        activation = BACKBONE_ACTIVATIONS[self.backbone_activation]
        for layer in range(self.backbone_layers):
            dense = torch_style_dense(self.backbone_units, features.shape[-1], f"backbone_{layer}",
                                      self.param_dtype)
            features = activation(dense(features))
            if layer > 0 and self.backbone_dropout > 0.0:
                features = nn.Dropout(self.backbone_dropout)(features, deterministic=deterministic)
        return features

    def _head(self, name: str, features: jax.Array) -> jax.Array:
        """One affine head (B, F) -> (B, H)."""
        return torch_style_dense(self.hidden_size, features.shape[-1], name, self.param_dtype)(features)

    @nn.compact
    def __call__(
        self, state: jax.Array, inputs: jax.Array, dt: Any = 1.0, *, deterministic: bool = True
    ) -> tuple[jax.Array, jax.Array]:
        """Advance the state by elapsed time ``dt``; returns ``(new_state, output)``, both (B, H)."""
        batch_size = inputs.shape[0]
        dt = as_time_delta(dt, batch_size, jnp.result_type(inputs, state))
        features = self._backbone(jnp.concatenate([inputs, state], axis=-1), deterministic)
        heads = {name: self._head(name, features) for name in cfc_head_names(self.mode)}
        extra = ()
        if self.mode == "pure":
            shape = (1, self.hidden_size)
            extra = tuple(self.param(name, nn.initializers.xavier_uniform(), shape, self.param_dtype)
                          for name in ("w_tau", "A"))
        new_state = cfc_update(self.mode, tuple(heads.values()), dt, extra)
        return new_state, new_state


def cfc_head_names(mode: str) -> tuple[str, ...]:
    """Names of the affine heads a CfC of ``mode`` has, in the order :func:`cfc_update` takes them."""
    return ("ff1",) if mode == "pure" else ("ff1", "ff2", "time_a", "time_b")


def cfc_update(mode: str, heads: tuple[jax.Array, ...], dt: jax.Array, extra: tuple[jax.Array, ...]) -> jax.Array:
    """New CfC state from the head outputs (each (B, H), order of :func:`cfc_head_names`) and ``dt`` (B, 1).

    ``extra`` is ``(w_tau, A)`` (each (1, H)) for ``mode='pure'`` (the paper's Cf-S) and ``()`` otherwise.
    """
    if mode == "pure":
        (ff1,), (w_tau, amplitude) = heads, extra
        decay = jnp.exp(-dt * (jnp.abs(w_tau) + jnp.abs(ff1)))
        return amplitude - amplitude * decay * ff1
    ff1, ff2, time_a, time_b = heads
    ff1, ff2 = jnp.tanh(ff1), jnp.tanh(ff2)
    gate = jax.nn.sigmoid(time_a * dt + time_b)
    if mode == "no_gate":
        return ff1 + gate * ff2
    return ff1 * (1.0 - gate) + gate * ff2
