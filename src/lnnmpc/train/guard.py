"""What keeps a run safe between chunks: a stop request (Ctrl-C / SIGTERM) that waits for the running chunk, and
the NaN/Inf checks that stop a diverged run before its state is accepted."""

from __future__ import annotations

import signal
import sys
import threading

import jax
import jax.numpy as jnp
import numpy as np


class StopRequest:
    """Turns the first SIGINT/SIGTERM into a flag checked between chunks; a second SIGINT aborts at once."""

    def __init__(self):
        self.requested, self._previous = None, {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        self.requested = signal.Signals(signum).name
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.stderr.write(f"\n{self.requested}: saving a checkpoint after the running chunk "
                         "(Ctrl-C again aborts without saving)\n")

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def all_finite(tree) -> jax.Array:
    """True where every floating leaf of ``tree`` is finite (a scalar; jit and vmap it over seeds)."""
    leaves = [x for x in jax.tree_util.tree_leaves(tree) if jnp.issubdtype(x.dtype, jnp.inexact)]
    return jnp.all(jnp.asarray([jnp.all(jnp.isfinite(x)) for x in leaves]))


def first_non_finite(metrics: dict) -> tuple[int, int, str] | None:
    """(seed, iteration, metric) of the first NaN/Inf among per-iteration metrics (seeds, iterations), or None."""
    first = None
    for name, values in metrics.items():
        if name in ("reward", "episode_return"):
            continue
        values = np.asarray(values)
        bad = ~np.isfinite(values.reshape(values.shape[0], values.shape[1], -1)).all(axis=2)
        if bad.any():
            where = np.argwhere(bad)  # (n, 2) rows of (seed, iteration)
            seed, index = where[np.argmin(where[:, 1])]
            if first is None or index < first[1]:
                first = (int(seed), int(index), name)
    return first
