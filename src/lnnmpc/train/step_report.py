"""Progress of compiled episode programs (the analyses' rollouts, :mod:`lnnmpc.analysis.rollout`), reported to
the host from inside their ``lax.scan`` over agent steps.

The programs are compiled once and reused across calls (and checkpoints), so the callback they hold is this
module's :func:`report_step` (:func:`lnnmpc.train.loop.play_episodes`' ``on_step``), and each call of a program
points it at that call's progress with :func:`reporting`. Without a progress set the callback does nothing.
XLA's persistent compilation cache keeps no program that holds a host callback, so the trainer's and ``make
eval``'s evaluation programs (which a later process may load from that cache) hold none and show no progress.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import jax

_SINK: dict = {"report": None, "done": 0, "total": 0}


def report_step(t) -> None:
    """Agent step ``t`` (0-based) of the running program is done: ``progress(t + 1, total)``. The callbacks are
    unordered, so only a step past the last one reported is forwarded."""
    report, done = _SINK["report"], int(t) + 1
    if report is not None and done > _SINK["done"]:
        _SINK["done"] = done
        report(done, _SINK["total"])


@contextlib.contextmanager
def reporting(progress: Callable[[int, int], None] | None, total: int) -> Iterator[None]:
    """Within the block, the programs' steps go to ``progress(done, total)`` (e.g.
    :class:`lnnmpc.train.report.StepProgress`; None: nowhere). Leaving it waits for every pending callback."""
    _SINK.update(report=progress, done=0, total=total)
    try:
        yield
    finally:
        jax.effects_barrier()
        _SINK["report"] = None
