"""Small pure math pieces of TD-MPC2 (Hansen et al., 2024), written for JAX.

Everything here is a jittable ``jnp`` function of arrays plus static Python configuration (bin counts, ranges,
group sizes), which is validated eagerly with ``ValueError`` messages that name the offending value.

Conventions that differ in form (not in value) from the PyTorch reference: reductions over the last axis drop that
axis (TD-MPC2 keeps it with ``keepdim=True``), so a log-probability or a loss of a batch ``(B, A)`` is ``(B,)``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

_HALF_LOG_2PI = 0.5 * float(np.log(2.0 * np.pi))  # 0.91893853...
_SQUASH_EPS = 1e-6  # TD-MPC2's epsilon inside log(1 - tanh(u)^2 + eps)


# ---------------------------------------------------------------------------------------------------------------
# symlog / symexp
# ---------------------------------------------------------------------------------------------------------------
def symlog(x: jax.Array) -> jax.Array:
    """sign(x) * log(1 + |x|), elementwise; any shape."""
    return jnp.sign(x) * jnp.log1p(jnp.abs(x))


def symexp(x: jax.Array) -> jax.Array:
    """sign(x) * (exp(|x|) - 1), elementwise inverse of :func:`symlog`; any shape."""
    return jnp.sign(x) * jnp.expm1(jnp.abs(x))


# ---------------------------------------------------------------------------------------------------------------
# Two-hot discrete regression over symlog bins
# ---------------------------------------------------------------------------------------------------------------
def _check_bins(num_bins: int, vmin: float, vmax: float) -> None:
    # TD-MPC2 also has num_bins == 0 (plain regression) and num_bins == 1 (symlog regression) modes, in which
    # ``two_hot`` returns a scalar rather than a distribution and soft cross-entropy is not defined; those modes are
    # never used by the published configuration, so they are rejected here to keep one shape contract.
    if not isinstance(num_bins, int) or num_bins < 2:
        raise ValueError(f"num_bins must be an int >= 2 (0/1 regression modes are unsupported), got {num_bins!r}")
    if not float(vmin) < float(vmax):
        raise ValueError(f"need vmin < vmax for the two-hot support, got vmin={vmin!r}, vmax={vmax!r}")


def bin_values(num_bins: int = 101, vmin: float = -10.0, vmax: float = 10.0) -> jax.Array:
    """Bin centres in symlog space, ``(num_bins,)``, evenly spaced from vmin to vmax inclusive."""
    _check_bins(num_bins, vmin, vmax)
    return jnp.linspace(vmin, vmax, num_bins)


def two_hot(x: jax.Array, num_bins: int = 101, vmin: float = -10.0, vmax: float = 10.0) -> jax.Array:
    """Soft two-hot encoding of symlog(x) clipped to [vmin, vmax].

    x: ``(...)`` scalars -> ``(..., num_bins)`` weights summing to 1, nonzero on the two bins around symlog(x) with
    weights linear in the distance (so ``weights · bin_values == clip(symlog(x))`` exactly).
    """
    _check_bins(num_bins, vmin, vmax)
    bin_size = (vmax - vmin) / (num_bins - 1)
    pos = (jnp.clip(symlog(x), vmin, vmax) - vmin) / bin_size  # in [0, num_bins - 1]
    lower = jnp.clip(jnp.floor(pos), 0, num_bins - 2)  # x == vmax: weight 0 on bin nb-2, weight 1 on bin nb-1
    frac = (pos - lower)[..., None]
    lower = lower.astype(jnp.int32)
    return (1.0 - frac) * jax.nn.one_hot(lower, num_bins, dtype=frac.dtype) + frac * jax.nn.one_hot(
        lower + 1, num_bins, dtype=frac.dtype
    )


def two_hot_inv(logits: jax.Array, num_bins: int = 101, vmin: float = -10.0, vmax: float = 10.0) -> jax.Array:
    """Expected value of a categorical over symlog bins, mapped back: symexp(softmax(logits) · bin_values).

    logits: ``(..., num_bins)`` -> ``(...)``.
    """
    if logits.shape[-1] != num_bins:
        raise ValueError(f"logits last axis {logits.shape[-1]} != num_bins {num_bins}")
    probs = jax.nn.softmax(logits, axis=-1)
    return symexp(jnp.sum(probs * bin_values(num_bins, vmin, vmax).astype(probs.dtype), axis=-1))


def soft_cross_entropy(
    logits: jax.Array, target: jax.Array, num_bins: int = 101, vmin: float = -10.0, vmax: float = 10.0
) -> jax.Array:
    """-sum(two_hot(target) * log_softmax(logits)) over bins.

    logits: ``(..., num_bins)``, target: ``(...)`` scalars (broadcastable) -> ``(...)`` losses.
    """
    if logits.shape[-1] != num_bins:
        raise ValueError(f"logits last axis {logits.shape[-1]} != num_bins {num_bins}")
    log_p = jax.nn.log_softmax(logits, axis=-1)
    return -jnp.sum(two_hot(target, num_bins, vmin, vmax).astype(log_p.dtype) * log_p, axis=-1)


# ---------------------------------------------------------------------------------------------------------------
# SimNorm
# ---------------------------------------------------------------------------------------------------------------
def simnorm(x: jax.Array, group_size: int = 8) -> jax.Array:
    """Simplicial normalisation: softmax within consecutive groups of ``group_size`` along the last axis.

    x: ``(..., D)`` with D divisible by group_size -> ``(..., D)``; each group of the output sums to 1.
    """
    if not isinstance(group_size, int) or group_size < 1:
        raise ValueError(f"group_size must be a positive int, got {group_size!r}")
    dim = x.shape[-1]
    if dim % group_size:
        raise ValueError(f"simnorm: last axis size {dim} is not divisible by group_size {group_size}")
    grouped = x.reshape(*x.shape[:-1], dim // group_size, group_size)
    return jax.nn.softmax(grouped, axis=-1).reshape(x.shape)


# ---------------------------------------------------------------------------------------------------------------
# Gaussian prediction loss (the stochastic LNN variants)
# ---------------------------------------------------------------------------------------------------------------
def gaussian_nll_loss(mean: jax.Array, sigma: jax.Array, target: jax.Array, beta: float = 0.0,
                      free_bits: float | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """β-NLL of ``target`` under N(mean, σ²), per sample, in nats per dimension, with optional free bits.

    mean, sigma, target: ``(..., D)``. Returns (loss, nll, floored), each ``(...)``:
    nll = mean over D of ½((t − μ)/σ)² + log σ + ½ log 2π, clipped from below at ``free_bits`` when given;
    loss = mean over D of stop_gradient(σ^(2β)) × the per-dimension NLL (β = 0: the NLL itself), except that a
    sample whose NLL is at or below ``free_bits`` (``floored``) passes no gradient. With β = 1 the mean's gradient
    is (μ − t)/D, the squared error's halved, instead of (μ − t)/(σ² D).
    """
    per_dim = 0.5 * jnp.square((target - mean) / sigma) + jnp.log(sigma) + _HALF_LOG_2PI
    nll = per_dim.mean(axis=-1)
    loss = nll if beta == 0 else (jax.lax.stop_gradient(sigma ** (2 * beta)) * per_dim).mean(axis=-1)
    if free_bits is None:
        return loss, nll, jnp.zeros(nll.shape, bool)
    floored = nll <= free_bits
    loss = jnp.where(floored, jax.lax.stop_gradient(jnp.maximum(loss, free_bits) if beta == 0 else loss), loss)
    return loss, jnp.maximum(nll, free_bits), floored


# ---------------------------------------------------------------------------------------------------------------
# Tanh-Gaussian policy
# ---------------------------------------------------------------------------------------------------------------
def gaussian_log_prob(eps: jax.Array, log_std: jax.Array) -> jax.Array:
    """Log-density of u = mean + exp(log_std) * eps under N(mean, exp(log_std)^2), from the standard noise eps.

    eps, log_std: ``(..., A)`` -> ``(...)`` (summed over the action axis).
    """
    return jnp.sum(-0.5 * jnp.square(eps) - log_std - _HALF_LOG_2PI, axis=-1)


def squash(mu: jax.Array, pi: jax.Array, log_pi: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """tanh-squash mean and sample and correct the log-density by the log-Jacobian of tanh.

    mu, pi: ``(..., A)`` pre-squash mean and sample; log_pi: ``(...)`` pre-squash log-density.
    Returns (tanh(mu), tanh(pi), log_pi - sum(log(relu(1 - tanh(pi)^2) + 1e-6))) with shapes ``(..., A)``,
    ``(..., A)``, ``(...)``; the 1e-6 is TD-MPC2's guard against log(0) at saturated actions.
    """
    mu = jnp.tanh(mu)
    pi = jnp.tanh(pi)
    log_det = jnp.sum(jnp.log(jax.nn.relu(1.0 - jnp.square(pi)) + _SQUASH_EPS), axis=-1)
    return mu, pi, log_pi - log_det


def log_std_from_raw(raw: jax.Array, min_log_std: float = -10.0, max_log_std: float = 2.0) -> jax.Array:
    """Smoothly bound a raw network output: min + 0.5 * (max - min) * (tanh(raw) + 1); any shape."""
    if not float(min_log_std) < float(max_log_std):
        raise ValueError(f"min_log_std={min_log_std!r} must be < max_log_std={max_log_std!r}")
    return min_log_std + 0.5 * (max_log_std - min_log_std) * (jnp.tanh(raw) + 1.0)


class TanhGaussianSample(NamedTuple):
    """Output of :func:`sample_tanh_gaussian`; all ``(..., A)`` except the ``(...)`` log_prob / scaled_entropy."""

    action: jax.Array  # tanh(mean + std * eps), in (-1, 1)
    log_prob: jax.Array  # exact log-density of ``action`` (change of variables through tanh)
    mean_action: jax.Array  # tanh(mean): the deterministic action
    scaled_entropy: jax.Array  # TD-MPC2 v2's entropy term for the policy loss (see sample_tanh_gaussian)


def sample_tanh_gaussian(
    key: jax.Array,
    mean: jax.Array,
    raw_log_std: jax.Array,
    min_log_std: float = -10.0,
    max_log_std: float = 2.0,
) -> TanhGaussianSample:
    """Reparameterised sample of TD-MPC2's tanh-Gaussian policy prior.

    mean, raw_log_std: ``(..., A)`` policy-head outputs (raw_log_std goes through :func:`log_std_from_raw`).

    Entropy scaling (choice, following the current official TD-MPC2 ``WorldModel.pi``): the policy loss uses
    ``scaled_entropy = -log_pi * (A * log_gauss) / (log_pi + 1e-8)`` where ``log_gauss`` is the *pre-squash* Gaussian
    log-density and ``log_pi`` the squashed one. Up to the 1e-8 that is exactly ``-A * log_gauss`` in value and in
    gradient, which is what is returned here (no division, so no blow-up when log_pi ~ 0). ``log_prob`` is the true
    squashed log-density (TD-MPC2's ``-info["entropy"]``). Policy loss: ``-(entropy_coef * scaled_entropy + Q)``.
    """
    log_std = log_std_from_raw(raw_log_std, min_log_std, max_log_std)
    eps = jax.random.normal(key, mean.shape, dtype=mean.dtype)
    log_gauss = gaussian_log_prob(eps, log_std)
    mean_action, action, log_prob = squash(mean, mean + eps * jnp.exp(log_std), log_gauss)
    return TanhGaussianSample(action, log_prob, mean_action, -mean.shape[-1] * log_gauss)


# ---------------------------------------------------------------------------------------------------------------
# Running percentile scale (TD-MPC2 RunningScale)
# ---------------------------------------------------------------------------------------------------------------
@struct.dataclass
class ScaleState:
    """Running scale of Q for the policy loss. value: ``()`` float32, starts at 1 and stays >= 1."""

    value: jax.Array

    @classmethod
    def create(cls) -> ScaleState:
        return cls(value=jnp.ones((), jnp.float32))


def batch_percentile_range(x: jax.Array, low: float = 5.0, high: float = 95.0) -> jax.Array:
    """P_high - P_low over all elements of x (linear interpolation between order statistics, as numpy's default and
    TD-MPC2's ``_percentile``); ``(...)`` -> ``()``. TD-MPC2 feeds ``(B, 1)`` Q values, so pooling equals its per-column
    percentile over the batch axis."""
    q = jnp.percentile(jnp.ravel(x), jnp.asarray([low, high], dtype=jnp.float32), method="linear")
    return q[1] - q[0]


def update_scale(state: ScaleState, x: jax.Array, tau: float = 0.01) -> ScaleState:
    """value <- lerp(value, max(P95(x) - P5(x), 1), tau). x: ``(...)`` batch of Q values (stop-gradient applied).

    As in TD-MPC2 there is no special first update: the value starts at 1 and is lerped from the first call on, and
    the clamp to >= 1 happens on the batch range, before the lerp.
    """
    if isinstance(tau, int | float) and not 0.0 <= tau <= 1.0:
        raise ValueError(f"tau must be in [0, 1], got {tau!r}")
    target = jnp.maximum(batch_percentile_range(jax.lax.stop_gradient(x)), 1.0).astype(state.value.dtype)
    return state.replace(value=state.value + tau * (target - state.value))


def apply_scale(state: ScaleState, x: jax.Array) -> jax.Array:
    """x / value (TD-MPC2's ``RunningScale.forward``; value >= 1 by construction, so this never amplifies)."""
    return x / state.value


# ---------------------------------------------------------------------------------------------------------------
# Misc
# ---------------------------------------------------------------------------------------------------------------
def polyak(target: Any, online: Any, tau: float) -> Any:
    """target + tau * (online - target), leafwise over matching pytrees (TD-MPC2: ``lerp_`` with tau = 0.01)."""
    if isinstance(tau, int | float) and not 0.0 <= tau <= 1.0:
        raise ValueError(f"tau must be in [0, 1], got {tau!r}")
    return jax.tree_util.tree_map(lambda t, o: t + tau * (o - t), target, online)


def discounted_weights(horizon: int, rho: float) -> jax.Array:
    """rho ** t for t = 0 .. horizon - 1, ``(horizon,)`` float32 (per-step loss weights)."""
    if not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"horizon must be a positive int, got {horizon!r}")
    return jnp.power(jnp.asarray(rho, jnp.float32), jnp.arange(horizon, dtype=jnp.float32))
