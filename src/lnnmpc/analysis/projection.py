"""UMAP projections of latents and true states to 2-D (thesis Figures 5.6–5.7), with ``umap-learn``."""

from __future__ import annotations

import numpy as np


def umap_2d(x: np.ndarray, *, seed: int = 0, n_neighbors: int = 15, min_dist: float = 0.1) -> np.ndarray:
    """2-D UMAP embedding (T, 2) of rows x (T, F). ``n_neighbors`` is capped at T − 1 for short inputs.

    Needs ``umap-learn`` (``pip install -e '.[analysis]'``); its first call compiles numba code (tens of seconds).
    """
    try:
        import umap
    except ImportError:
        raise ImportError("UMAP projections need umap-learn: pip install -e '.[analysis]'") from None
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 3:
        raise ValueError(f"need x (T, F) with T >= 3 rows, got shape {x.shape}")
    reducer = umap.UMAP(n_components=2, n_neighbors=min(n_neighbors, x.shape[0] - 1), min_dist=min_dist,
                        random_state=seed)
    return np.asarray(reducer.fit_transform(x))


def log_speed(v: np.ndarray) -> np.ndarray:
    """Colour values log(|v| + 1e-3) of a velocity (T,): the thesis colours by the logarithm of the velocity;
    the absolute value (and the offset for v = 0) make it defined for negative and zero velocities."""
    return np.log(np.abs(np.asarray(v, dtype=np.float64)) + 1e-3)
