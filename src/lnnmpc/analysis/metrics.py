"""Numerical pieces of the representation analyses (NumPy, float64, no JAX).

Shapes: T time steps, N latent units, K state variables, A action dims, d observation dims.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def quadratic_features(z: np.ndarray) -> np.ndarray:
    """[z, z²] (T, 2N) of latents z (T, N): the thesis's quadratic combination of latent units (§5.3)."""
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2:
        raise ValueError(f"latents must be (T, N), got shape {z.shape}")
    return np.concatenate([z, z**2], axis=1)


def ridge_fit(x: np.ndarray, y: np.ndarray, alpha: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Ridge regression with an unpenalised intercept: (W (F, K), b (K,)) minimising ‖x W + b − y‖² + α‖W‖².

    x (T, F), y (T, K). Solved in closed form on centred data: W = (xcᵀxc + αI)⁻¹ xcᵀyc, b = ȳ − x̄ W.
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.ndim != 2 or y.ndim != 2 or x.shape[0] != y.shape[0]:
        raise ValueError(f"need x (T, F) and y (T, K) with the same T, got {x.shape} and {y.shape}")
    if not alpha >= 0:
        raise ValueError(f"alpha must be >= 0, got {alpha!r}")
    x_mean, y_mean = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - x_mean, y - y_mean
    w = np.linalg.solve(xc.T @ xc + alpha * np.eye(x.shape[1]), xc.T @ yc)
    return w, y_mean - x_mean @ w


def pearson(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pearson r (K,) between the columns of a (T, K) and b (T, K) (thesis eq. 5.3); NaN for a constant column."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ac, bc = a - a.mean(axis=0), b - b.mean(axis=0)
    denom = np.sqrt((ac**2).sum(axis=0) * (bc**2).sum(axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(denom > 0, (ac * bc).sum(axis=0) / np.where(denom > 0, denom, 1.0), np.nan)


def ridge_pearson(z: np.ndarray, states: np.ndarray, alpha: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Pearson r (K,) of each state variable with its ridge prediction from [z, z²], and the predictions (T, K).

    z (T, N) latents, states (T, K) true state variables of the same steps (fitted and scored on the same
    data, as in the thesis: r measures how linearly readable the state is from the quadratic features).
    """
    x = quadratic_features(z)
    w, b = ridge_fit(x, states, alpha)
    predicted = x @ w + b
    return pearson(states, predicted), predicted


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to [−π, π)."""
    return (np.asarray(angle, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def balance_start(pole_angle: np.ndarray, threshold: float = 0.3, hold: int = 25) -> int:
    """First step of the balance phase of a cartpole episode (T if it never balances).

    The balance phase starts at the first step t from which the pole stays upright, |wrapped angle| <
    ``threshold`` rad (0.3 rad ≈ 17°, cos > 0.955), for ``hold`` consecutive agent steps (25 = 1 s); the
    swing-up phase is [0, t), the balance phase [t, T) (the thesis's two successive phases). ``pole_angle`` (T,)
    in rad, 0 = upright.
    """
    upright = np.abs(wrap_angle(pole_angle)) < threshold
    if hold < 1:
        raise ValueError(f"hold must be >= 1, got {hold!r}")
    runs = np.convolve(upright.astype(np.int64), np.ones(hold, dtype=np.int64), mode="valid")
    starts = np.flatnonzero(runs == hold)
    return int(starts[0]) if starts.size else int(upright.shape[0])


def effective_rank(z: np.ndarray) -> float:
    """Effective rank (Roy & Vetterli, 2007) of a matrix z (T, D): exp(H(p)), H(p) = −Σ_k p_k log p_k over
    p_k = σ_k / Σ σ (the singular values, zeros dropped). Between 1 (rank one) and min(T, D) (equal singular
    values). The thesis's eq. 5.5 prints the exponent without the minus sign; this is the published definition.
    """
    sigma = np.linalg.svd(np.asarray(z, dtype=np.float64), compute_uv=False)
    if sigma.size == 0 or sigma.sum() <= 0:
        raise ValueError(f"effective rank needs a non-zero matrix, got shape {np.shape(z)}")
    p = sigma / sigma.sum()
    p = p[p > 0]
    return float(np.exp(-(p * np.log(p)).sum()))


def k_step_predictions(predict: Callable, step: Callable, z: np.ndarray, actions: np.ndarray, starts: np.ndarray,
                       k: int) -> np.ndarray:
    """Open-loop predictions (S, k, d) of a model rolled forward on its own predictions from each start t.

    From z ← z_t: for j = 0..k−1, ô_{t+j+1} = predict(z, a_{t+j}), z ← step(z, a_{t+j}). ``predict`` / ``step``
    take a batch (S, N), (S, A) and return (S, d) / (S, N). z (T, N): latents after reading o_t; actions (T, A).
    """
    current, predictions = np.asarray(z)[starts], []
    for j in range(k):
        a = np.asarray(actions)[starts + j]
        predictions.append(np.asarray(predict(current, a), dtype=np.float64))
        current = step(current, a)
    return np.stack(predictions, axis=1)


def k_step_errors(predict: Callable, step: Callable, z: np.ndarray, actions: np.ndarray, targets: np.ndarray,
                  k: int, stride: int = 1) -> np.ndarray:
    """Squared prediction errors (S, k) of k-step open-loop rollouts (:func:`k_step_predictions`).

    Starts t = 0, stride, ... with t + k < T; error_j = mean over dims of (ô_{t+j+1} − targets_{t+j+1})².
    targets (T, d): what the model predicts (the delivered observations for OP models). Column 0 is the
    one-step error.
    """
    z, actions, targets = (np.asarray(v) for v in (z, actions, targets))
    if not (z.shape[0] == actions.shape[0] == targets.shape[0]):
        raise ValueError(f"z, actions and targets need the same T, got {z.shape}, {actions.shape}, {targets.shape}")
    if k < 1 or stride < 1 or z.shape[0] <= k:
        raise ValueError(f"need k >= 1, stride >= 1 and T > k, got k={k}, stride={stride}, T={z.shape[0]}")
    starts = np.arange(0, z.shape[0] - k, stride)
    predicted = k_step_predictions(predict, step, z, actions, starts, k)
    truth = targets[starts[:, None] + np.arange(1, k + 1)[None, :]]
    return ((predicted - truth) ** 2).mean(axis=2)
