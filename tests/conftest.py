"""Shared test setup: no OpenGL for dm_control (CI has no display), small CPU-only JAX, heaviest files first."""

import gc
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

# One XLA compilation cache for the whole test session, made by the controlling process and inherited by the
# xdist workers and the trainer subprocesses: a program that several files compile alike is compiled once, and
# the suite neither reads nor fills the user's cache (~/.cache/lnnmpc/xla), so its time does not depend on what
# ran on the machine before. Removed when the session ends.
if "LNNMPC_TEST_XLA_CACHE" not in os.environ:
    os.environ["LNNMPC_TEST_XLA_CACHE"] = tempfile.mkdtemp(prefix="lnnmpc-test-xla-")
    _OWNS_CACHE = True
else:
    _OWNS_CACHE = False
os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ["LNNMPC_TEST_XLA_CACHE"]
os.environ["LNNMPC_COMPILE_CACHE"] = os.environ["LNNMPC_TEST_XLA_CACHE"]

# The suite is compile-bound (the CPU learning test: 210 of its 267 s alone are XLA compiling its four
# programs). XLA's backend optimisation level 1 instead of 2 cut that test to 224 s with the same execution time
# (level 0 compiles faster still but ran three times slower). XLA's CPU fusion emitters (MLIR, on by default in
# jaxlib 0.10) are the slower path to compile: turned off, the XLA compile time of test_trainer_run's four programs
# (compiled one after the other, CPU only) fell from 78-91 s to 64-66 s while their execution got ~20% slower
# (a small part there). Tests only: trainer subprocesses get these through LNNMPC_TEST_XLA_FLAGS
# (tests/test_trainer_run.py), runs of `make train` keep XLA's defaults.
TEST_XLA_FLAGS = "--xla_backend_optimization_level=1 --xla_cpu_use_fusion_emitters=false"
os.environ["LNNMPC_TEST_XLA_FLAGS"] = TEST_XLA_FLAGS
if TEST_XLA_FLAGS not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {TEST_XLA_FLAGS}".strip()

# Most in-process test programs run for milliseconds, so for them compiling is the whole cost: JAX's
# jax_disable_most_optimizations (XLA backend level 0 and no expensive LLVM passes) compiles them ~30% faster (a
# training chunk 18.9 s against 26.9 s at level 1) and runs them ~4x slower (11.0 s against 2.8 s). With level 0
# in every in-process file, a fresh-clone suite took 984.6 s of pytest against 1,134.0 s (user CPU 30.1 min
# against 35.2), but the in-process evaluations of test_trainer_run ran slower (their episodes are long) and two
# tests that compare two programs bit for bit or through walker's chaotic contacts differed by round-off (1 ulp in
# a restarted walker's qpos; 4e-3 after 8 contact steps). So test_trainer_run keeps level 1 for the whole file
# (OPTIMISED_FILES), and those two walker comparisons (test_env_api's step_or_reset, test_env_solver's unrolled
# solver) are marked full_optimisation (_test_compile_effort below); their cartpole cases agree bit for bit and to
# 1e-5 at level 0 too and compile there (22 s against 36 s, 18 s against 24 s). Every other file turns the flag on
# for its duration (_compile_effort below). Trainer subprocesses keep level 1.
OPTIMISED_FILES = ("test_trainer_run.py",)

# Tracing is the suite's other big cost (JAX builds millions of short-lived objects over a heap of ~1 GB of
# modules and programs), and Python's cyclic GC at its default thresholds (700, 10, 10) keeps walking that heap:
# perf on a trainer subprocess that only traces and loads cached programs put 9.4% of its CPU time in the GC,
# 2.3% with these thresholds (in-process test files: ~5%). Nothing is computed differently; unreachable cycles are
# only freed later. The xdist workers (which import this file) use them, and the trainer subprocesses get them
# through LNNMPC_TEST_GC_THRESHOLDS (tests/test_trainer_run.py).
TEST_GC_THRESHOLDS = (100_000, 50, 100)
os.environ["LNNMPC_TEST_GC_THRESHOLDS"] = ",".join(map(str, TEST_GC_THRESHOLDS))
gc.set_threshold(*TEST_GC_THRESHOLDS)

# Test files by measured cost on a 2-core CPU (compile-bound), most expensive first. With `--dist loadfile`
# xdist hands out whole files; in collection order (see pytest_configure) the long files start at once on both
# workers and the many short ones fill the gaps at the end (longest processing time first). xdist's default order
# (most tests first) would leave the eight-test trainer file, the longest, for last. Files not
# listed keep pytest's order after these.
# The learning check lives in test_trainer_run.py (its reference run is the learning run; a separate in-process
# learning file cost ~110-200 s of compiling the same kinds of programs again).
# The order comes from the per-file sums of worker seconds in `pytest -n 2 --dist loadfile --durations=0` on a
# fresh clone (re-measure with it when files grow; every file over ~20 s is listed). The workers end within
# seconds of each other, so the order is not what costs: the suite is CPU-bound and compile-bound, mostly MJX (a
# vmapped cartpole step_or_reset lowers to ~12K StableHLO ops and compiles in ~10 s at level 1 on 2 cores, and
# every program that steps or resets an environment holds one). XLA flags tried without gain on that step: parallel
# codegen split 1, the concurrency-optimised scheduler off, copy insertion without region analysis; on
# test_trainer_run's reference run, LLVM's expensive passes off. An Env's physics is traced once per process
# (env.py, _traced_once) and build_loop, evaluate and video take their Envs from setup.shared_env, so a file's
# programs on one task share that trace. Dated suite and per-file timings are in tests/TIMES.md.
HEAVY_FILES = ("test_trainer_run.py", "test_lnn_training.py", "test_env_api.py", "test_experiment_scripts.py",
               "test_lnn_losses.py", "test_analysis.py", "test_train_loop.py", "test_env_solver.py", "test_env_fast.py",
               "test_tdmpc2.py", "test_cells.py", "test_benchmark_in_scan.py", "test_exploration.py",
               "test_device_batch.py", "test_env_parity.py", "test_trainer_config.py", "test_env_corruptions.py",
               "test_actor.py", "test_lnn_agents.py", "test_tdmpc2_model.py")


def pytest_configure(config):
    """Keeps the collection order for xdist's file scheduling (pytest-xdist >= 3.8 reorders unless told not to)."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False
    config.addinivalue_line("markers", "full_optimisation: the test compiles with XLA's optimisations (level 1) in "
                                       "a file that otherwise compiles with jax_disable_most_optimizations")


def pytest_unconfigure(config):
    """The process that made the session's compilation cache removes it."""
    if _OWNS_CACHE:
        shutil.rmtree(os.environ["LNNMPC_TEST_XLA_CACHE"], ignore_errors=True)


def _file_rank(item) -> int:
    name = item.path.name
    return HEAVY_FILES.index(name) if name in HEAVY_FILES else len(HEAVY_FILES)


def pytest_collection_modifyitems(session, config, items):
    """Reorders whole files heaviest first (stable: the order inside a file is kept)."""
    items.sort(key=_file_rank)


def _module_disables_optimizations(request) -> bool:
    """Whether the requesting test's file compiles with jax_disable_most_optimizations (not in OPTIMISED_FILES)."""
    return request.path.name not in OPTIMISED_FILES


@pytest.fixture(autouse=True, scope="module")
def _compile_effort(request):
    """Compiles the module's programs with jax_disable_most_optimizations unless it is in OPTIMISED_FILES."""
    import jax

    jax.config.update("jax_disable_most_optimizations", _module_disables_optimizations(request))
    yield
    jax.config.update("jax_disable_most_optimizations", False)


@pytest.fixture(autouse=True)
def _test_compile_effort(request):
    """A test marked ``full_optimisation`` compiles with optimisations (its module's fixtures keep the module's)."""
    import jax

    if request.node.get_closest_marker("full_optimisation") is None:
        yield
        return
    jax.config.update("jax_disable_most_optimizations", False)
    yield
    jax.config.update("jax_disable_most_optimizations", _module_disables_optimizations(request))
