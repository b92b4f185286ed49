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
# Measured so (this checkout, this 2-core CPU, 2026-12-02): 720.0 s of pytest, 435 passed (the runs of that day
# vary by ~15% with the machine's other load: before the per-test marks, the in-process dm_control evaluations
# and the video launches at level 0, 745.7 s and 822.3 s; with all but the last, 677.6 s and 791.8 s; 1,048.3 s
# on a fresh clone earlier that day).
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
# Measured 2026-11-26 (fresh clone, `make test`, before that merge): trainer_run ~470 s, env_fast ~130, analysis
# ~120, lnn_training ~115, benchmark_in_scan ~75, env_solver ~72, tdmpc2 ~66, lnn_agents ~65, train_loop ~47,
# cells ~47, env_parity ~34, env_corruptions ~27.
# Measured 2026-12-02 (fresh clone, `pytest -n 2 --dist loadfile --durations=0`, 912 s): per-file sums 1,789 worker
# seconds: trainer_run 586, env_fast 151, lnn_training 132, analysis 102, train_loop 99, env_api 95, lnn_agents 84,
# env_solver 63, exploration 59, benchmark_in_scan 56, cells 50, tdmpc2 50, experiments_studies 44. The workers
# ended 17 s apart (912 against 1,789 / 2), so the order is not what costs: the suite is CPU-bound, and a shorter
# one needs less compiling. Most of it is MJX: a vmapped cartpole step_or_reset lowers to ~12K StableHLO ops
# (1.26 M characters), traces in ~3 s (1.2 s unvmapped) and compiles in ~10 s at level 1 on 2 cores, and every
# program that steps or resets an environment holds one (the trainer's seed chunk: 13K ops, 12.9 s alone; its
# training chunk 21.5K, 23.0 s). XLA flags tried without gain: on that step (one core) parallel codegen split 1,
# the concurrency-optimised scheduler off, copy insertion without region analysis (15.2 s without them, 15.8-16.4
# with); on test_trainer_run's reference run LLVM's expensive passes off (104 s against 98 s). Since 6285eb4 an Env's
# physics is traced once per process and shared by the programs that call it (env.py, _traced_once): a cached launch
# of that run 77 s -> 71 s (its training chunk lowered in 4.1 s instead of 10.1), results bit for bit unchanged.
# build_loop, evaluate and video take their Envs from setup.shared_env (one per task, physics, options and x64 mode
# in a process), so a file's loads of a run and validations of several agents on one task share that trace (a
# walker validate's eval_shape 3.0 s -> 0.1 s), and test_trainer_run's three video commands share one launch. Fresh
# clones, back to back (2026-12-02, `bash .ci/run`): 825.6 s of pytest, 868 s in all, 438 passed, against 925.7 s
# and 969 s (437 passed) for the commit before (test_trainer_run alone: 375.6 s against 440.7 s).
# Re-measured 2026-12-03 (worktree of ec09d8b, same command, 668 s): trainer_run 397, env_fast 124, env_api 85,
# lnn_training 81, train_loop 76 (~45 after its evaluation-key test moved to _ToyEnv), lnn_agents 70, analysis 51,
# env_solver 51, exploration 45, cells 44, experiments_studies 40, benchmark_in_scan 36, tdmpc2 34, env_parity 24,
# actor 23, env_corruptions 22, tdmpc2_model 20, trainer_config 17; the rest under 15 s each. env_api, exploration
# and experiments_studies were not listed, so they started after every listed file.
HEAVY_FILES = ("test_trainer_run.py", "test_env_fast.py", "test_env_api.py", "test_lnn_training.py",
               "test_lnn_agents.py", "test_analysis.py", "test_env_solver.py", "test_train_loop.py",
               "test_exploration.py", "test_cells.py", "test_experiments_studies.py", "test_benchmark_in_scan.py",
               "test_tdmpc2.py", "test_env_parity.py", "test_actor.py", "test_env_corruptions.py",
               "test_tdmpc2_model.py", "test_trainer_config.py")


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
