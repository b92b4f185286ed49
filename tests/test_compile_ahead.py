"""The trainer's programs compiled ahead of time (lnnmpc.train.sharding.compile_ahead): in parallel threads or
one by one at their first call, falling back to jit on other arguments; a stopped or crashed run does not wait
for compilations still running."""

from __future__ import annotations

import time

import numpy as np
import pytest

_NEVER_COMPILES = """
import threading
from lnnmpc.train import cli
from lnnmpc.train.sharding import compile_ahead, pending_compilations

class Lowered:  # a compilation that never ends (Python would join its thread at exit for ever)
    def compile(self):
        threading.Event().wait()

class Jitted:
    def lower(self, *args):
        return Lowered()

def run_command(args):  # the trainer, stopped or crashing while a program still compiles in the background
    compile_ahead([(Jitted(), ())])
    assert pending_compilations() == 1
    print("stopping", flush=True)
    raise {error}

cli.run_command = run_command
cli.main(["train", "--task", "cartpole-balance"])
"""


@pytest.mark.parametrize("error, status, message", [
    ("KeyboardInterrupt", 130, ""), ("RuntimeError('boom')", 1, "RuntimeError: boom")])
def test_a_stopped_or_crashed_run_exits_without_waiting_for_background_compilations(error, status, message):
    import subprocess
    import sys

    script = _NEVER_COMPILES.replace("{error}", error)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == status, done.stderr
    assert done.stdout == "stopping\n"
    assert "not waiting for 1 program(s) still compiling in the background" in done.stderr
    assert message in done.stderr


def test_programs_compiled_ahead_in_parallel_run_and_fall_back_on_other_arguments(capsys):
    import jax
    import jax.numpy as jnp

    from lnnmpc.train.sharding import compile_ahead, pending_compilations

    double, total = jax.jit(lambda x: 2 * x), jax.jit(lambda x, y: (x * y).sum())
    done = []
    first, second = compile_ahead([(double, (jnp.ones(3),)), (total, (jnp.ones(3), jnp.ones(3)))],
                                  on_done=lambda index, program: done.append((index, program)))
    assert second.ready().compiled is not None and first.ready().compiled is not None  # waits for the threads
    assert pending_compilations() == 0
    assert sorted(index for index, _ in done) == [0, 1] and {id(p) for _, p in done} == {id(first), id(second)}
    for program in (first, second):
        assert program.lower_s > 0 and program.compile_s > 0 and program.done_at <= time.perf_counter()
    np.testing.assert_array_equal(first(jnp.arange(3.0)), [0.0, 2.0, 4.0])
    assert float(second(jnp.arange(3.0), jnp.full(3, 2.0))) == 6.0
    assert first.compiled is not None  # the ahead-of-time executable ran
    np.testing.assert_array_equal(first(jnp.arange(4.0)), [0.0, 2.0, 4.0, 6.0])  # another shape: jit compiles it
    assert first.compiled is None and "refused its arguments" in capsys.readouterr().err


def test_programs_lowered_now_compile_one_by_one_when_first_called():
    import jax
    import jax.numpy as jnp

    from lnnmpc.train.sharding import compile_ahead, pending_compilations

    double, total = jax.jit(lambda x: 2 * x), jax.jit(lambda x, y: (x * y).sum())
    done = []
    first, second = compile_ahead([(double, (jnp.ones(3),)), (total, (jnp.ones(3), jnp.ones(3)))], parallel=False,
                                  on_done=lambda index, program: done.append(index))
    assert first.lower_s > 0 and second.lower_s > 0  # both lowered here, in the order given
    assert pending_compilations() == 0 and done == [] and not first.done() and not second.done()
    assert first.compiled is None and second.compiled is None  # nothing compiled yet
    np.testing.assert_array_equal(second.ready()(jnp.arange(3.0), jnp.full(3, 2.0)), 6.0)  # compiled on this thread
    assert done == [1] and second.done() and second.compile_s > 0 and not first.done()
    np.testing.assert_array_equal(first(jnp.arange(3.0)), [0.0, 2.0, 4.0])  # the first call compiles it
    assert done == [1, 0] and first.done() and isinstance(first.compiled, jax.stages.Compiled)
    np.testing.assert_array_equal(first(jnp.arange(3.0) + 1), [2.0, 4.0, 6.0])
    assert done == [1, 0]  # compiled once
