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
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

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

    def abstract(self, jitted: Callable, *args):
        """The result of ``jitted(*args)`` as ShapeDtypeStructs placed like :meth:`put` (nothing run or compiled):
        example arguments for compiling, ahead of time, the programs that take that result."""
        shapes = jax.eval_shape(jitted, *args)
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

    Calls run the executable; arguments it was not compiled for (another shape, dtype or placement: a
    :class:`jax.stages.Compiled` refuses them with TypeError/ValueError) fall back to the jitted function for
    good, which compiles as usual. Both run the same program, so results do not depend on which one ran."""

    def __init__(self, jitted: Callable, compiled=None):
        self.jitted, self.compiled = jitted, compiled

    def __call__(self, *args):
        if self.compiled is not None:
            try:
                return self.compiled(*args)
            except (TypeError, ValueError) as error:
                sys.stderr.write(f"\nahead-of-time program refused its arguments ({str(error)[:200]}); "
                                 "compiling it again\n")
                self.compiled = None
        return self.jitted(*args)


def compile_ahead(jobs: list[tuple[Callable, tuple]]) -> list[AheadOfTime]:
    """Compiles every ``(jitted, example_args)`` job at once, in threads (XLA compiles without the GIL, so
    several programs build in parallel on a machine with several cores: the trainer's seed phase, update burst,
    training chunk and evaluation programs then cost about the slowest one's time instead of the sum).

    The programs are traced and lowered one after the other on this thread, each handed to a compiling thread as
    soon as it is lowered. Traced concurrently in threads, JAX can lay out shared inner functions differently: the
    same computation, but other programs for XLA's persistent compilation cache, which a resumed run or an
    evaluation (jitted one at a time) then misses and compiles again."""
    with ThreadPoolExecutor(max_workers=max(1, len(jobs))) as pool:
        futures = [pool.submit(jitted.lower(*args).compile) for jitted, args in jobs]
        return [AheadOfTime(jitted, future.result()) for (jitted, _), future in zip(jobs, futures, strict=True)]
