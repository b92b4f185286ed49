"""The trainer end to end at CI size, in subprocesses as a user runs it: run folder, the agent learns, kill/Ctrl-C
and exact resume, seeds sharded over two (forced host) devices, NaN stop, evaluation on MJX and on dm_control, video.
(Evaluations, which need no fresh process, run the CLI or ``lnnmpc.evaluate`` in this one; the three video
commands share one launch.)

One reference run (2 seeds) is trained once per module; the other runs use the same configuration and hit
XLA's persistent compilation cache (a folder per test session), so they mostly pay for tracing. The reference is
also the suite's learning run: a CPU-sized TD-MPC2 on cartpole-swingup through the schedule of SPEC §1 (seed
phase, update burst, one update per agent step), long enough to beat its untrained self by a wide margin.
"""

from __future__ import annotations

import csv
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

CONFIG = ["--task", "cartpole-swingup", "--small", "--model-size", "1", "--seeds", "2", "--steps", "2800",
          "--seed-steps", "1000", "--eval-every", "600", "--eval-episodes", "2", "--batch-size", "64",
          "--checkpoint-every", "600", "--replay-capacity", "3000", "--keep-checkpoints", "10"]
# Seed phase to 1,000 env steps (500 iterations), then the 902 iterations that reach 2,800 (two of them reset
# episodes and take no step) in 4 equal chunks of 226 (at most eval_every's 300 iterations each); an evaluation and
# a checkpoint at the first chunk boundary past each multiple of 600 (not at 2,352) and at the end, 2,804.
CHECKPOINTS = [1000, 1450, 1902, 2804]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("xla-cache"))


def _env(cache: str, **extra) -> dict:
    """The subprocess's environment: the test session's XLA flags (conftest) plus ``extra``'s, nothing else's."""
    flags = f"{os.environ.get('LNNMPC_TEST_XLA_FLAGS', '')} {extra.pop('XLA_FLAGS', '')}".strip()
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    return {**env, "JAX_PLATFORMS": "cpu", "LNNMPC_COMPILE_CACHE": cache, "MUJOCO_GL": "disable", "XLA_FLAGS": flags,
            **extra}


# `python -m lnnmpc.train.cli` (runpy runs the module as -m does), with the test session's GC thresholds (conftest:
# the subprocesses mostly trace and load cached programs, where the default thresholds cost ~7% of their CPU time).
_LAUNCH = ("import gc, os, runpy; gc.set_threshold(*map(int, os.environ.get('LNNMPC_TEST_GC_THRESHOLDS', "
           "'700,10,10').split(','))); runpy.run_module('lnnmpc.train.cli', run_name='__main__', alter_sys=True)")


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-c", _LAUNCH, *args]


def _run(args: list[str], cache: str, timeout: float = 600, **extra) -> subprocess.CompletedProcess:
    return subprocess.run(_cli(*args), env=_env(cache, **extra), capture_output=True, text=True, timeout=timeout)


def _steps(run) -> list[int]:
    folder = os.path.join(run, "checkpoints")
    return sorted(int(n) for n in os.listdir(folder) if n.isdigit()) if os.path.isdir(folder) else []


def _wait_for_checkpoint(proc: subprocess.Popen, run, above: int, timeout: float = 400) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        done = [s for s in _steps(run) if s > above]
        if done:
            return done[-1]
        assert proc.poll() is None, f"the run ended before a checkpoint above {above}: {proc.communicate()}"
        time.sleep(0.05)
    raise AssertionError("no checkpoint in time")


def _rows(path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def reference(tmp_path_factory, cache):
    """An uninterrupted run of CONFIG, keeping each evaluation's policy (``--eval-policies``)."""
    run = tmp_path_factory.mktemp("runs") / "reference"
    result = _run([*CONFIG, "--out", str(run), "--compile-ahead", "on", "--eval-policies"], cache)  # others: auto
    assert result.returncode == 0, result.stderr[-3000:]
    return run


def test_run_folder_holds_config_logs_checkpoints_plot_and_summary(reference):
    import json

    files = {p.name for p in reference.iterdir()}
    assert {"config.json", "train.csv", "eval.csv", "curve.png", "summary.md", "checkpoints", "policy.npz"} <= files
    from lnnmpc.train.policy_file import policy_step, snapshot_steps

    assert policy_step(str(reference)) == CHECKPOINTS[-1]  # rewritten with each checkpoint: the newest's
    assert snapshot_steps(str(reference)) == CHECKPOINTS  # --eval-policies: one per evaluation (each at a checkpoint)
    config = json.loads((reference / "config.json").read_text())
    assert config["config"]["seeds"] == 2 and config["config"]["replay_capacity"] == 3000
    assert config["num_devices"] == 1
    rows = _rows(reference / "eval.csv")
    assert set(rows[0]) == {"env_step", "seed", "episode", "return", "effective_rank"}
    assert all(1 <= float(r["effective_rank"]) <= 16 for r in rows)  # small tdmpc2: latent 16
    steps = sorted({int(r["env_step"]) for r in rows})
    assert steps == CHECKPOINTS and len(rows) == 4 * len(steps)  # 2 seeds x 2 episodes
    assert all(0 <= float(r["return"]) <= 1000 for r in rows)
    train = _rows(reference / "train.csv")
    assert {"episode_return", "total_loss", "consistency_loss"} <= set(train[0])
    assert all(np.isfinite(float(r["total_loss"])) for r in train if int(r["env_step"]) > CHECKPOINTS[0])
    assert _steps(reference) == CHECKPOINTS
    summary = (reference / "summary.md").read_text()
    assert "cartpole-swingup · tdmpc2 · 2 seed(s)" in summary and "**Final return" in summary
    assert "| agent | tdmpc2 (model size 1M, small) |" in summary
    seed_mean = lambda step, seed: np.mean([float(r["return"]) for r in rows
                                            if int(r["env_step"]) == step and int(r["seed"]) == seed])
    recent = [np.mean([seed_mean(step, seed) for seed in (0, 1)]) for step in steps[-3:]]
    assert (f"Mean of the last 3 evaluations {np.mean(recent):.1f} (from {min(recent):.1f} to {max(recent):.1f})"
            in summary)
    finals = [f"seed {seed} {seed_mean(steps[-1], seed):.1f} (its best " for seed in (0, 1)]
    assert all(text in summary for text in finals) and "Per seed at the last evaluation: " in summary
    assert summary.count("\n") < 40  # one screen
    (start,) = config["provenance"]  # one start: where the run came from
    assert start["command"].startswith("python -m lnnmpc.train.cli --task cartpole-swingup --small")
    launched = [*CONFIG, "--out", str(reference), "--compile-ahead", "on", "--eval-policies"]
    assert start["command"].endswith(f"--out {reference} --compile-ahead on --eval-policies")
    assert start["argv"][1:] == launched
    import jax

    assert start["versions"]["jax"] == jax.__version__ and start["versions"]["mujoco-mjx"]
    assert f"Started by `{start['command']}`." in summary and "| code | " in summary
    assert (reference / "curve.png").stat().st_size > 10_000
    assert (reference / "training.png").stat().st_size > 10_000
    timing = _rows(reference / "timing.csv")
    phases = [r["phase"] for r in timing]
    assert phases[:5] == ["startup", "compile", "initialise", "seed_phase", "update_burst"]
    startup = float(timing[0]["seconds"])  # the process before the run's clock: Python, imports, checks
    assert 0.5 < startup < 300
    marks = start["startup"]  # where that time went: the ends of the start-up steps, in order, inside the row
    assert list(marks) == ["imports", "devices", "built", "validated"]
    assert 0 < marks["imports"] <= marks["devices"] <= marks["built"] <= marks["validated"] <= startup + 0.01
    assert {"train_chunk", "evaluate", "checkpoint"} <= set(phases)
    chunks = [r for r in timing if r["phase"] == "train_chunk"]
    assert all(int(r["env_steps_per_seed"]) > 0 and float(r["env_steps_per_s_all_seeds"]) > 0 for r in chunks)
    seeded = next(int(r["env_steps_per_seed"]) for r in timing if r["phase"] == "seed_phase")
    assert sum(int(r["env_steps_per_seed"]) for r in chunks) + seeded == steps[-1]
    # compile.csv: every program compiled ahead, the training chunk's lowered first; the compile phase waited for
    # all but the evaluation's and the training chunk's (ready_s counts from that phase's start, so lowering and
    # compiling fit inside it); the chunk's rest, if any, is a second compile row right before the first chunk
    compiled = _rows(reference / "compile.csv")
    assert {r["program"] for r in compiled} == {"train_chunk", "seed_chunk", "update_burst", "init", "finite",
                                                "evaluate"} and len(compiled) == 6
    assert all(float(r["ready_s"]) >= float(r["compile_s"]) > 0 and float(r["lower_s"]) > 0 for r in compiled)
    ready = {r["program"]: float(r["ready_s"]) for r in compiled}
    began = {r["program"]: float(r["ready_s"]) - float(r["compile_s"]) for r in compiled}  # compilation's start
    assert began["train_chunk"] == min(began.values())  # lowered first, so compiling first
    assert all(ready[name] <= float(timing[1]["seconds"]) for name in ready if name not in ("evaluate", "train_chunk"))
    first_chunk = phases.index("train_chunk")
    assert phases.count("compile") == 1 + (phases[first_chunk - 1] == "compile")
    assert ready["train_chunk"] <= sum(float(r["seconds"]) for r in timing[1:first_chunk]) + 5.0  # + bookkeeping


def test_killed_and_interrupted_run_resumes_to_the_same_eval_rows(reference, tmp_path, cache):
    run = tmp_path / "resumed"
    # 1: SIGKILL right after the first checkpoint (the seed phase).
    proc = subprocess.Popen(_cli(*CONFIG, "--out", str(run)), env=_env(cache), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    first = _wait_for_checkpoint(proc, run, -1)
    proc.kill()
    proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    # 2: resume; Ctrl-C after its next checkpoint: saves a checkpoint after the running chunk, exits 130.
    proc = subprocess.Popen(_cli("train", "--resume", str(run)), env=_env(cache), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    second = _wait_for_checkpoint(proc, run, first)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err[-2000:]
    assert "checkpoint saved" in err and f"make train RESUME={run}" in err and "Traceback" not in err
    interrupted = _steps(run)[-1]
    assert second <= interrupted < CHECKPOINTS[-1]
    # 3: resume to the end with --eval-prior turned on (a resume may change it: the training is the same): the
    # same evaluation rows (bit for bit) and per-episode training rows; the resumed evaluations' rows gain the
    # policy prior's return of each episode, the earlier rows keep theirs and an empty ``prior_return``; the
    # progress line and summary give the prior's mean beside MPPI's. (The reference, eval_prior off, logs no
    # such column: test_run_folder_holds_config_logs_checkpoints_plot_and_summary.)
    result = _run(["train", "--resume", str(run), "--eval-prior", "--compile-ahead", "on"], cache)  # (the new
    # evaluation program, the prior's play added, compiles beside the first chunks instead of before its first use)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"resuming {run} at {interrupted:,} env steps" in result.stderr
    assert (run / "train.csv").read_text() == (reference / "train.csv").read_text()
    with open(run / "eval.csv") as f:
        assert csv.DictReader(f).fieldnames == ["env_step", "seed", "episode", "return", "effective_rank",
                                                "prior_return"]
    rows, planner = _rows(run / "eval.csv"), _rows(reference / "eval.csv")
    # MPPI's episodes as without the prior's, bit for bit (the prior's play in a scan of their own)
    assert [{k: v for k, v in r.items() if k != "prior_return"} for r in rows] == planner
    assert all(r["prior_return"] == "" for r in rows if int(r["env_step"]) <= interrupted)
    resumed = [r for r in rows if int(r["env_step"]) > interrupted]
    prior = np.asarray([float(r["prior_return"]) for r in resumed])
    assert len(resumed) >= 4 and np.all((prior >= 0) & (prior <= 1000))  # 2 seeds x 2 episodes, each its own
    assert not np.allclose(prior, [float(r["return"]) for r in resumed])  # another actor
    last = prior[-4:]
    assert f"(prior {last.mean():.1f})" in result.stderr
    import json

    config = json.loads((run / "config.json").read_text())
    assert config["config"]["eval_prior"] is True
    starts = config["provenance"]  # the start and both resumes
    assert [entry["command"].endswith(f"train --resume {run}") for entry in starts] == [False, True, False]
    assert starts[2]["command"].endswith(f"train --resume {run} --eval-prior --compile-ahead on")
    assert starts[0]["time"] <= starts[1]["time"] <= starts[2]["time"]
    summary = (run / "summary.md").read_text()
    assert "3 starts (resumed)" in summary and f"Started by `{starts[0]['command']}`." in summary
    assert f"The policy prior alone on the same episodes: {last.mean():.1f} ± " in summary


def test_seeds_sharded_over_two_devices_give_the_unsharded_state(reference, tmp_path, cache):
    """Seed phase, update burst and evaluation of the 2 seeds sharded over 2 CPU devices (one seed each): the same
    training state as the unsharded reference up to float32 round-off (XLA may pick other kernels for a batch of
    one; evaluation returns are not compared, MPPI amplifies such differences). The environment amplifies it too:
    under the tests' XLA level 1 (conftest) a pole velocity in the replay drifted by 4.4e-5 after ~190 steps, hence
    2e-4 (with the current CONFIG the largest difference is 5.9e-6, in the replay's observations, 3% of the
    tolerance); a sharding mistake (a seed's keys, states or data swapped or shared) differs by O(1). Then the
    sharded run resumes to the next checkpoint, its state restored into the sharded placement."""
    import json

    import jax

    from lnnmpc.train.checkpoint import restore_checkpoint
    from lnnmpc.train.evaluate import load_policy

    run = tmp_path / "sharded"
    seeded = CHECKPOINTS[0]
    result = _run([*CONFIG, "--steps", str(seeded), "--out", str(run)], cache,
                  XLA_FLAGS="--xla_force_host_platform_device_count=2")
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((run / "config.json").read_text())["num_devices"] == 2 and _steps(run) == [seeded]
    policy = load_policy(str(reference), seeded)
    like = jax.eval_shape(jax.vmap(policy.loop.init), jax.random.split(jax.random.key(0), 2))
    one, two = (restore_checkpoint(str(folder), seeded, like)[0] for folder in (reference, run))
    floats = lambda tree: [np.asarray(x, np.float64) for x in jax.tree_util.tree_leaves(tree)
                           if jax.numpy.issubdtype(x.dtype, jax.numpy.floating) and x.size]
    for part in ("agent", "replay", "env"):
        for x, y in zip(floats(getattr(one, part)), floats(getattr(two, part)), strict=True):
            np.testing.assert_allclose(x, y, atol=2e-4, rtol=2e-4, err_msg=part)
    assert len(_rows(run / "eval.csv")) == 4
    # resumed, sharded again: its checkpoint restored straight into the sharded programs' placement, which the
    # programs compiled ahead (here also on 2 cores) accept as they are (else they would fall back and recompile)
    result = _run(["train", "--resume", str(run), "--steps", str(CHECKPOINTS[1]), "--compile-ahead", "on"], cache,
                  XLA_FLAGS="--xla_force_host_platform_device_count=2")
    assert result.returncode == 0, result.stderr[-3000:]
    assert _steps(run) == CHECKPOINTS[:2] and "refused its arguments" not in result.stderr
    assert {(int(r["env_step"]), int(r["seed"])) for r in _rows(run / "eval.csv")} == {
        (step, seed) for step in CHECKPOINTS[:2] for seed in (0, 1)}


def test_nan_in_a_loss_stops_the_run_and_keeps_the_last_good_checkpoint(reference, tmp_path, monkeypatch, cache):
    import lnnmpc
    from lnnmpc.train import runfolder, trainer

    monkeypatch.setenv("LNNMPC_COMPILE_CACHE", cache)
    run = tmp_path / "diverged"
    shutil.copytree(reference, run)
    # back to the second checkpoint: the resume keeps the budget, hence the chunk length, whose program is cached
    for step in CHECKPOINTS[2:]:
        shutil.rmtree(run / "checkpoints" / str(step))
    before = _steps(run)
    eval_before = [r for r in _rows(reference / "eval.csv") if int(r["env_step"]) <= before[-1]]
    real = trainer._Run.chunk_fn

    def poisoned(self, name, length):
        fn = real(self, name, length)

        def call(ts):
            ts, out = fn(ts)
            loss = np.array(out["total_loss"])
            loss[1, 7] = np.nan
            return ts, {**out, "total_loss": loss}
        return call

    monkeypatch.setattr(trainer._Run, "chunk_fn", poisoned)
    # compile_ahead off: the first training chunk diverges, so the run never evaluates (nothing to compile ahead)
    config = runfolder.saved_config(str(run), compile_ahead="off")
    with pytest.raises(lnnmpc.TrainingDiverged) as error:
        lnnmpc.train(config, resume=str(run))
    last = before[-1]
    assert before == CHECKPOINTS[:2] and last == 1450
    assert f"non-finite total_loss (NaN or Inf) at env step ~{last + 16:,}, seed 1" in str(error.value)
    assert f"last good checkpoint ({last:,} env steps) is kept" in str(error.value)
    assert _steps(run) == before and _rows(run / "eval.csv") == eval_before


def test_evaluate_a_chosen_checkpoint_on_mjx(reference, monkeypatch, cache):
    import lnnmpc

    monkeypatch.setenv("LNNMPC_COMPILE_CACHE", cache)
    result = lnnmpc.evaluate(str(reference), episodes=4, checkpoint=1450, verbose=False)
    assert result.returns.shape == (2, 4) and result.checkpoint == 1450 and result.backend == "mjx"
    assert np.all((result.returns >= 0) & (result.returns <= 1000))
    assert os.path.basename(result.path) == "mjx-clean-1450.csv" and len(_rows(result.path)) == 8
    with pytest.raises(lnnmpc.ConfigError, match="checkpoint 500 is not in .*; available: 1000, 1450, 1902, 2804"):
        lnnmpc.evaluate(str(reference), checkpoint=500)
    # The trained planner's own values given as overrides: a rebuilt agent that plays the same episodes exactly (the
    # same program, so no compilation; that other values plan differently is the unit test's and [57]'s)
    planned = lnnmpc.evaluate(str(reference), episodes=4, checkpoint=1450, planner={"iterations": 2, "plan_horizon": 3},
                              verbose=False)
    assert os.path.basename(planned.path) == "mjx-iterations2-plan_horizon3-clean-1450.csv"
    assert [r["planner"] for r in _rows(planned.path)] == ["iterations=2 plan_horizon=3"] * 8
    np.testing.assert_array_equal(planned.returns, result.returns)
    with pytest.raises(lnnmpc.ConfigError, match="'num_q' is not a planner setting; an evaluation may change only: "):
        lnnmpc.evaluate(str(reference), planner={"num_q": 3})


def test_run_folder_without_checkpoints_evaluates_from_its_policy_file(reference, tmp_path, monkeypatch, cache):
    """A run folder brought back from a GPU has no checkpoints (they hold the replay buffer): ``evaluate`` takes
    its ``policy.npz`` and returns exactly what the newest checkpoint gives, and at an earlier evaluation's step
    that evaluation's policy (``policies/``) what its checkpoint gives."""
    import lnnmpc

    monkeypatch.setenv("LNNMPC_COMPILE_CACHE", cache)
    back = tmp_path / "back"
    shutil.copytree(reference, back, ignore=shutil.ignore_patterns("checkpoints", "evals", "videos"))
    from_policy = lnnmpc.evaluate(str(back), episodes=4, seed=3, verbose=False)
    from_checkpoint = lnnmpc.evaluate(str(reference), episodes=4, seed=3, verbose=False, out=str(tmp_path / "c.csv"))
    assert from_policy.checkpoint == from_checkpoint.checkpoint == CHECKPOINTS[-1]
    np.testing.assert_array_equal(from_policy.returns, from_checkpoint.returns)
    assert from_policy.returns.std() > 0  # episodes differ: a real evaluation, not a constant
    # an earlier evaluation's policy (--eval-policies) plays exactly what that step's checkpoint plays
    earlier = lnnmpc.evaluate(str(back), episodes=4, seed=3, checkpoint=1450, verbose=False)
    at_checkpoint = lnnmpc.evaluate(str(reference), episodes=4, seed=3, checkpoint=1450, verbose=False,
                                    out=str(tmp_path / "c1450.csv"))
    np.testing.assert_array_equal(earlier.returns, at_checkpoint.returns)
    assert not np.array_equal(earlier.returns, from_policy.returns)  # another policy than the newest
    shutil.rmtree(back / "policies")
    with pytest.raises(lnnmpc.ConfigError, match=f"checkpoint 1450 is not in .*; available: {CHECKPOINTS[-1]}"):
        lnnmpc.evaluate(str(back), checkpoint=1450)
    os.remove(back / "policy.npz")
    with pytest.raises(lnnmpc.ConfigError, match="has no complete checkpoint, no policy.npz and no policies/"):
        lnnmpc.evaluate(str(back))


def test_trained_agent_beats_its_untrained_self(reference, cache):
    """The reference run's final agent against freshly initialised parameters (zero-initialised reward and Q heads: MPPI
    cannot tell actions apart), same evaluation keys, 4 deterministic episodes per seed, through ``mjx_evaluator``, the
    program ``lnnmpc.evaluate`` runs (a compilation-cache hit after the test above). Both seeds must improve by a wide
    margin. Measured on CPU (jax 0.10.2), seed means over 5 draws of initial parameters and evaluation keys: untrained
    0.5-39.7, the final agent 201-309. Training is not monotone at this size: the same run's agent at 2,196 steps scored
    91-135 (at 1,598: 119-192), and another CPU's round-off can end the run in such a dip, so the bounds leave room for
    it while no untrained draw comes near them."""
    import jax

    from lnnmpc.train.evaluate import load_policy, mjx_evaluator
    from lnnmpc.train.setup import enable_compile_cache

    enable_compile_cache(cache)
    policy = load_policy(str(reference))
    assert policy.checkpoint == CHECKPOINTS[-1]
    agent = policy.loop.agent
    evaluate = mjx_evaluator(agent, policy.loop.env, episodes=4, seeds=2)
    untrained = jax.jit(jax.vmap(agent.init))(jax.random.split(jax.random.key(1), 2))
    before = evaluate(untrained, jax.random.key(0)).mean(axis=1)
    after = evaluate(policy.agent_state, jax.random.key(0)).mean(axis=1)
    assert (before < 60).all(), before  # no swing-up: little reward
    assert (after > before + 40).all() and after.mean() > 90, (before, after)


def test_mjx_evaluator_replays_each_training_evaluation(reference, cache):
    """Every evaluation of eval.csv replayed outside the trainer: that step's policy, the trainer's evaluation key
    for it (split in turn from ``key(seed + 10,000)``; ``acrobot_starts.trainer_evaluation_key``, which this
    checks), through ``mjx_evaluator`` (another compiled program: it records no latents). The same episodes must
    give the same returns, so that a standalone evaluation's numbers and a run's curve differ only by the episodes
    they play (``lnnmpc.evaluate``'s default key is ``key(0)``: other episodes). The evaluator plays the trainer's 2
    episodes per seed, not the 4 of the tests above: 4 episodes with the same key start from the same 2 states and 2
    more (tests/test_train_loop.py), but another batch width is another program, and on an AVX-512 CPU (2026-12-05)
    its round-off moved these chaotic episodes' returns by up to 11 at step 1,000 (bit for bit equal at width 2);
    with ``make eval``'s default of 10 episodes the widths match the trainer's."""
    from lnnmpc.analysis.acrobot_starts import trainer_evaluation_key
    from lnnmpc.train.evaluate import load_policy, mjx_evaluator, policy_at
    from lnnmpc.train.setup import enable_compile_cache

    enable_compile_cache(cache)
    policy = load_policy(str(reference))
    shape = (policy.config.seeds, policy.config.eval_episodes)  # (2, 2): the reference run's
    evaluate = mjx_evaluator(policy.loop.agent, policy.loop.eval_env, episodes=shape[1], seeds=shape[0])
    rows = _rows(reference / "eval.csv")
    for index, step in enumerate(CHECKPOINTS):
        key = trainer_evaluation_key(policy.config.seed, index)
        logged = np.zeros(shape)
        for row in (r for r in rows if int(r["env_step"]) == step):
            logged[int(row["seed"]), int(row["episode"])] = float(row["return"])
        replayed = evaluate(policy_at(policy, str(reference), step).agent_state, key)
        np.testing.assert_allclose(replayed, logged, rtol=1e-4, atol=1e-2, err_msg=f"evaluation at {step}")


def _cli_in_process(capsys, *args: str, refused: bool = False) -> tuple[str, str]:
    """The CLI run in this process on ``args`` (as ``make eval`` runs it, without a Python start-up and imports of
    its own): its stdout and stderr. It must succeed (no SystemExit), or with ``refused`` exit with status 2."""
    from lnnmpc.train.cli import main

    capsys.readouterr()
    if refused:
        with pytest.raises(SystemExit) as stopped:
            main(list(args))
        assert stopped.value.code == 2
    else:
        main(list(args))
    return capsys.readouterr()


def test_make_eval_on_dm_control_with_noise_and_delay_prints_mean_and_std(reference, monkeypatch, cache, capsys):
    """The latest checkpoint's policy on the original dm_control simulator, 2 seeds x 2 episodes."""
    monkeypatch.setenv("LNNMPC_COMPILE_CACHE", cache)
    stdout, stderr = _cli_in_process(capsys, "eval", str(reference), "--episodes", "2", "--backend", "dm_control",
                                     "--obs", "noise=0.1,delay=2")
    assert "checkpoint 2,804 on dm_control with delay2-noise0.1: return " in stdout and " ± " in stdout
    # a live line on stderr while the episodes run, ending at the episode's last agent step
    assert "500/500 agent steps of 2 seed(s) x 2 episodes on dm_control  " in stderr
    rows = _rows(reference / "evals" / "dm_control-delay2-noise0.1-2804.csv")
    assert [(int(r["seed"]), int(r["episode"])) for r in rows] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    returns = np.asarray([float(r["return"]) for r in rows])
    assert np.all((returns > 0) & (returns <= 1000)) and {r["backend"] for r in rows} == {"dm_control"}
    mean = float(stdout.split("return ")[1].split(" ±")[0])
    assert mean == pytest.approx(returns.mean(), abs=0.06)


def _refused(capsys, *args: str) -> str:
    """The CLI run in this process on ``args``, which it must refuse with exit status 2: its stderr."""
    return _cli_in_process(capsys, *args, refused=True)[1]


def test_eval_with_the_policy_prior_alone_on_mjx_and_dm_control(reference, monkeypatch, cache, capsys):
    """``--actor prior``: the same checkpoint and episodes with the policy prior acting instead of MPPI, in a CSV
    of its own on each backend; a misspelt actor is refused before anything runs. (4 episodes: the planner's
    evaluation program is the one the tests above compiled.)"""
    import lnnmpc

    monkeypatch.setenv("LNNMPC_COMPILE_CACHE", cache)
    planner = lnnmpc.evaluate(str(reference), episodes=4, seed=5, verbose=False)
    prior = lnnmpc.evaluate(str(reference), episodes=4, seed=5, actor="prior", verbose=False)
    assert os.path.basename(prior.path) == "mjx-prior-seed5-clean-2804.csv" and prior.returns.shape == (2, 4)
    assert {r["eval_seed"] for r in _rows(prior.path)} == {"5"}  # another seed's episodes: a file of their own
    assert {r["actor"] for r in _rows(prior.path)} == {"prior"} and {r["actor"] for r in _rows(planner.path)} == {
        "planner"}
    assert np.all((prior.returns >= 0) & (prior.returns <= 1000))
    assert not np.allclose(prior.returns, planner.returns)  # another actor, not MPPI under another name
    stdout, _ = _cli_in_process(capsys, "eval", str(reference), "--episodes", "1", "--backend", "dm_control",
                                "--actor", "prior", "--deterministic")  # on this started CPU backend: no change
    assert "checkpoint 2,804 on dm_control with clean, acting with the prior: return " in stdout
    rows = _rows(reference / "evals" / "dm_control-prior-clean-2804.csv")  # seed 0: the name without a seed
    assert len(rows) == 2 and {r["actor"] for r in rows} == {"prior"} and {r["eval_seed"] for r in rows} == {"0"}
    assert "unknown actor 'mpc'; known: planner, prior" in _refused(capsys, "eval", str(reference), "--actor", "mpc")


# The video launches: offscreen OpenGL, and jax_disable_most_optimizations (their few agent steps run in
# milliseconds, compiling the acting program is their cost; conftest)
_FILMING = {"MUJOCO_GL": "egl", "JAX_DISABLE_MOST_OPTIMIZATIONS": "1"}

# Several CLI commands one after the other in one Python process, as separate launches would run them: each one's
# exit status, stdout and stderr go to the JSON file named by the first argument (a list of {returncode, stdout,
# stderr}); the second argument is the JSON list of the commands' argument lists.
_LAUNCH_MANY = """
import contextlib, gc, io, json, os, sys
gc.set_threshold(*map(int, os.environ.get('LNNMPC_TEST_GC_THRESHOLDS', '700,10,10').split(',')))
from lnnmpc.train.cli import main
results = []
for argv in json.loads(sys.argv[2]):
    out, err, code = io.StringIO(), io.StringIO(), 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main(argv)
        except SystemExit as stop:
            code = stop.code or 0
    results.append({"returncode": code, "stdout": out.getvalue(), "stderr": err.getvalue()})
with open(sys.argv[1], "w") as f:
    json.dump(results, f)
"""


@pytest.fixture(scope="module")
def videos(reference, tmp_path_factory, cache):
    """The video commands of the tests below, launched together in one subprocess (offscreen OpenGL must be chosen
    before MuJoCo loads, so not in this one): one Python start-up, import and policy environment for all three
    (~12 s each on a 2-core CPU). Returns their folder and {name: CompletedProcess} in launch order: ``planner``
    (one episode to folder/episode.mp4), ``prior`` (the prior acting, default file) and ``films`` (three episodes
    into folder/films)."""
    import json

    folder = tmp_path_factory.mktemp("videos")
    commands = {
        "planner": ["video", str(reference), "--out", str(folder / "episode.mp4"), "--max-steps", "12", "--width",
                    "96", "--height", "72"],
        "prior": ["video", str(reference), "--actor", "prior", "--max-steps", "12", "--width", "96", "--height", "72"],
        "films": ["video", str(reference), "--out", str(folder / "films"), "--episodes", "3", "--falls-below", "1e9",
                  "--max-steps", "6", "--width", "64", "--height", "48"],
    }
    results = folder / "results.json"
    launch = subprocess.run([sys.executable, "-c", _LAUNCH_MANY, str(results), json.dumps(list(commands.values()))],
                            env=_env(cache, **_FILMING), capture_output=True, text=True, timeout=600)
    assert launch.returncode == 0, launch.stderr[-3000:]
    outcomes = json.loads(results.read_text())
    return folder, {name: subprocess.CompletedProcess(argv, o["returncode"], o["stdout"], o["stderr"])
                    for (name, argv), o in zip(commands.items(), outcomes, strict=True)}


def test_video_renders_an_episode_with_egl_to_mp4(reference, videos, capsys):
    import imageio_ffmpeg

    folder, launched = videos
    out = folder / "episode.mp4"
    result = launched["planner"]
    assert result.returncode == 0, result.stderr[-3000:]
    assert "12 frames at 50 fps" in result.stdout
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    frames = [np.frombuffer(f, np.uint8).reshape(72, 96, 3) for f in reader]
    assert meta["size"] == (96, 72) and len(frames) == 12
    assert frames[-1][40:].std() > 5  # a rendered scene below the text band, not a blank image
    # the policy prior alone on the same episode: its own default file, the same first picture, other actions
    prior = launched["prior"]
    assert prior.returncode == 0, prior.stderr[-3000:]
    path = reference / "videos" / "2804-prior.mp4"
    assert f"12 frames at 50 fps -> {path}" in prior.stdout
    reader = imageio_ffmpeg.read_frames(str(path))
    next(reader)
    prior_frames = [np.frombuffer(f, np.uint8).reshape(72, 96, 3).astype(int) for f in reader]
    assert len(prior_frames) == 12
    first, last = (np.abs(prior_frames[i][40:] - frames[i][40:]).mean() for i in (0, -1))
    # one initial state, then the prior's actions: 2.2 then 4.8 on one CPU, 1.8 then 2.6 on another (AMD EPYC)
    assert 0 < first < 3 and last > 1.2 * first
    assert "unknown actor 'mpc'; known: planner, prior" in _refused(capsys, "video", str(reference), "--actor", "mpc")


def test_video_films_many_episodes_into_a_folder_and_keeps_the_falls(videos):
    """``video --episodes 3``: three episodes at once, from three initial states, each streamed to its own MP4 of
    every agent step; ``keep_films`` then deletes the films of episodes that did not end below the threshold."""
    import imageio_ffmpeg

    from lnnmpc.train.video import keep_films

    folder, launched = videos
    folder = folder / "films"
    result = launched["films"]
    assert result.returncode == 0, result.stderr[-3000:]
    assert "returns of 3 episodes: mean " in result.stdout and "filmed below 1e+09: 0 (" in result.stdout
    films = sorted(folder.iterdir())
    assert [f.name for f in films] == ["episode-0.mp4", "episode-1.mp4", "episode-2.mp4"]
    first_frames = []
    for film in films:
        reader = imageio_ffmpeg.read_frames(str(film))
        next(reader)
        frames = [np.frombuffer(f, np.uint8).reshape(48, 64, 3) for f in reader]
        assert len(frames) == 6
        first_frames.append(frames[0].astype(int))
    assert np.abs(first_frames[0] - first_frames[1]).max() > 0  # other initial states, other pictures
    kept = keep_films(np.array([50.0, 400.0, 10.0]), [str(f) for f in films], below=100.0)
    assert kept == {0: (50.0, str(films[0])), 2: (10.0, str(films[2]))}
    assert sorted(f.name for f in folder.iterdir()) == ["episode-0.mp4", "episode-2.mp4"]

