"""The seed axis across devices: one program, ``vmap`` over seeds, the seed axis sharded with ``jax.sharding``.

Every array of the training state carries the seed axis first. With several devices, :class:`SeedPlacement` puts
that axis on a 1-D mesh of the devices (``NamedSharding(mesh, P("seeds"))``) and compiles each piece of the loop
with that sharding for inputs and outputs, so XLA partitions the one ``vmap``-ed program and every device runs its
share of the seeds (seeds are independent: no communication except gathering results to the host). With one
device nothing is sharded and the programs are the plain ``jit(vmap(...))`` ones.

Arrays are always *committed* to their devices (``put``), also with one device: a restored checkpoint is
committed, and a fresh run must hand the compiled programs the same kind of inputs so that both compile to the
same programs (and hit the same persistent-cache entries).
"""

from __future__ import annotations

import functools
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec, SingleDeviceSharding

from lnnmpc.train.config import ConfigError


def device_count_for(seeds: int, available: int, requested: int | None = None) -> int:
    """Devices to shard ``seeds`` over: ``requested`` (must divide seeds), else the most that divide ``seeds``."""
    if requested is not None:
        if requested > available:
            raise ConfigError(f"devices={requested} but only {available} device(s) exist")
        if seeds % requested:
            raise ConfigError(f"seeds={seeds} cannot be split evenly over devices={requested}; "
                              f"use a divisor of {seeds} not above {available}")
        return requested
    return max(d for d in range(1, min(seeds, available) + 1) if seeds % d == 0)


class SeedPlacement:
    """Compiles per-seed functions for a batch of seeds, sharded over ``num_devices`` devices."""

    def __init__(self, num_devices: int):
        self.num_devices = num_devices
        if num_devices > 1:
            mesh = Mesh(np.asarray(jax.devices()[:num_devices]), ("seeds",))
            self.sharding = NamedSharding(mesh, PartitionSpec("seeds"))
        else:
            self.sharding = SingleDeviceSharding(jax.devices()[0])

    def put(self, tree):
        """Places (commits) a seed-batched pytree (host or device arrays) on the devices."""
        return jax.device_put(tree, self.sharding)

    def abstract(self, shapes):
        """Seed-batched ShapeDtypeStructs (e.g. from ``jax.eval_shape``) placed like :meth:`put` (nothing run or
        compiled): example arguments for compiling, ahead of time, the programs that take such a pytree."""
        return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=self.sharding,
                                                            weak_type=s.weak_type), shapes)

    def compile(self, fn: Callable, *static, in_axes=0) -> Callable:
        """``jit(vmap(fn(..., *static)))`` over the seed axis; static arguments are bound, not traced."""
        batched = jax.vmap(functools.partial(_call_with_static, fn, static), in_axes=in_axes)
        if self.num_devices == 1:
            return jax.jit(batched)
        return jax.jit(batched, in_shardings=self.sharding, out_shardings=self.sharding)


def _call_with_static(fn, static, *args):
    return fn(*args, *static)


class AheadOfTime:
    """A jitted function with an executable compiled ahead of time for one set of example arguments.

    ``compiled`` is the executable or a future of it (:func:`compile_ahead` compiles in the background): the first
    call waits for it (:meth:`ready` waits without calling). Calls run the executable; arguments it was not compiled
    for (another shape, dtype or placement: a :class:`jax.stages.Compiled` refuses them with TypeError/ValueError)
    fall back to the jitted function for good, which compiles as usual. Both run the same program, so results do
    not depend on which one ran. ``lower_s`` / ``compile_s``: seconds spent lowering (tracing included) and
    compiling it, ``done_at``: ``time.perf_counter()`` when its compilation ended (None until then)."""

    def __init__(self, jitted: Callable, compiled=None, lower_s: float = 0.0):
        self.jitted, self.compiled, self.lower_s = jitted, compiled, lower_s
        self.compile_s, self.done_at = 0.0, None
        self.compile_later: Callable | None = None  # set for a program lowered now and compiled on first use

    def done(self) -> bool:
        """Whether the compilation has ended (the first call would neither wait nor compile)."""
        return self.compile_later is None and (not isinstance(self.compiled, Future) or self.compiled.done())

    def ready(self) -> AheadOfTime:
        """Waits for the background compilation, if any (its errors are raised here), or compiles a program
        lowered with ``parallel=False`` on this thread; returns self."""
        if self.compile_later is not None:
            compile_now, self.compile_later = self.compile_later, None
            self.compiled = compile_now()
        if isinstance(self.compiled, Future):
            self.compiled = self.compiled.result()
        return self

    def __call__(self, *args):
        if self.ready().compiled is not None:
            try:
                return self.compiled(*args)
            except (TypeError, ValueError) as error:
                sys.stderr.write(f"\nahead-of-time program refused its arguments ({str(error)[:200]}); "
                                 "compiling it again\n")
                self.compiled = None
        return self.jitted(*args)


def compile_ahead(jobs: list[tuple[Callable, tuple]],
                  on_done: Callable[[int, AheadOfTime], None] | None = None,
                  parallel: bool = True) -> list[AheadOfTime]:
    """Starts compiling every ``(jitted, example_args)`` job at once, in threads, and returns without waiting
    (XLA compiles without the GIL, so several programs build in parallel on a machine with several cores: the
    trainer's seed phase, update burst, training chunk and evaluation programs then cost about the slowest one's
    time instead of the sum). Each returned :class:`AheadOfTime` waits for its own program when first called, so a
    program needed later (an evaluation) finishes compiling while the first ones run. ``on_done(index, program)``
    is called from the compiling thread as each compilation ends (its timings set).

    The programs are traced and lowered one after the other on this thread, in the order given (put the one that
    takes longest to compile first), each handed to a compiling thread as soon as it is lowered. Traced
    concurrently in threads, JAX can lay out shared inner functions differently: the same computation, but other
    programs for XLA's persistent compilation cache, which a resumed run or an evaluation (jitted one at a time)
    then misses and compiles again.

    ``parallel=False`` lowers every program now, in the order given, and compiles none: each compiles on this
    thread when first called (or :meth:`AheadOfTime.ready`). The order in which programs are traced decides
    details of the programs (XLA's private functions are numbered as JAX first meets them: tracing the evaluation
    before the training chunk adds one to the chunk's), so lowering in a fixed order gives the same programs, and
    the same persistent-cache entries, whether compiled in threads or one by one."""
    pool = ThreadPoolExecutor(max_workers=max(1, len(jobs)), thread_name_prefix="compile-ahead") if parallel else None
    programs = []
    for index, (jitted, args) in enumerate(jobs):
        start = time.perf_counter()
        lowered = jitted.lower(*args)
        program = AheadOfTime(jitted, lower_s=time.perf_counter() - start)
        if pool is None:
            program.compile_later = functools.partial(_compile, lowered, program, index, on_done)
        else:
            program.compiled = pool.submit(_compile, lowered, program, index, on_done)
            _track(program.compiled)
        programs.append(program)
    if pool is not None:
        pool.shutdown(wait=False)  # the threads end with their compilations
    return programs


_pending: set[Future] = set()  # compile_ahead's compilations that have not ended yet
_pending_lock = threading.Lock()


def _track(future: Future) -> None:
    with _pending_lock:
        _pending.add(future)
    future.add_done_callback(_untrack)  # (at once if it has ended already)


def _untrack(future: Future) -> None:
    with _pending_lock:
        _pending.discard(future)


def pending_compilations() -> int:
    """How many programs :func:`compile_ahead` is still compiling in the background. Python joins their threads
    when it exits, so a process that stops early (Ctrl-C in the first chunks, before the evaluation's program is
    ready) would otherwise wait for them: ``lnnmpc.train.cli`` exits at once instead."""
    with _pending_lock:  # (a future is done before its callbacks run: count by done(), not by the set's size)
        return sum(not future.done() for future in _pending)


def _compile(lowered, program: AheadOfTime, index: int, on_done):
    start = time.perf_counter()
    compiled = lowered.compile()
    program.done_at = time.perf_counter()
    program.compile_s = program.done_at - start
    if on_done is not None:
        on_done(index, program)
    return compiled
