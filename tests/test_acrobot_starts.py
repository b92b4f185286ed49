"""``lnnmpc.analysis.acrobot_starts``: evaluation starts as the environment resets them, their energy against MuJoCo's,
the start-adjusted mean against an independent float64 least-squares computation, and the command on committed GPU
runs (the trainer's logged returns must follow the recomputed starts' energy)."""

import csv
import json
import os

import jax
import mujoco
import numpy as np
import pytest

from lnnmpc.analysis import acrobot_starts as starts
from lnnmpc.train import provenance

RESULTS = os.path.join(os.path.dirname(__file__), "..", "experiments", "results",
                       "cfc-acrobot-recipe-ar4-ar8-h100-200k")
RUNS = [os.path.join(RESULTS, f"acrobot-recipe-ar4-seed{seed}") for seed in (1, 2, 3)]


@pytest.fixture(scope="module")
def env():
    from lnnmpc.train import runfolder
    from lnnmpc.train.setup import config_env

    return config_env(runfolder.saved_config(RUNS[0]), {})


def test_start_qpos_are_the_joint_positions_env_reset_puts_the_episodes_in(env):
    from lnnmpc.train.loop import evaluation_keys

    key = jax.random.key(7)
    qpos = starts.start_qpos(env, key, seeds=2, episodes=3)
    assert qpos.shape == (2, 3, 2)
    for seed, seed_key in enumerate(jax.random.split(key, 2)):
        resets, _ = evaluation_keys(seed_key, 3)
        reset = jax.vmap(env.reset)(resets)
        np.testing.assert_array_equal(qpos[seed], np.asarray(reset.physics.qpos))
    assert np.all(np.abs(qpos) <= np.pi) and len(np.unique(qpos)) == qpos.size  # uniform angles, all different


def test_dm_control_starts_are_those_of_dm_controls_seeded_tasks(env):
    """``cli eval --backend dm_control --seed 3``'s episode e starts where dm_control's task seeded with 3 + e puts
    the chain (``acrobot_ceiling.dm_control_envs``, another path into dm_control)."""
    from lnnmpc.analysis import acrobot_ceiling as ac

    qpos = starts.dm_control_start_qpos(env, 3, 4)
    reference = [np.array(sim.physics.data.qpos) for sim in ac.dm_control_envs([3, 4, 5, 6])]
    np.testing.assert_array_equal(qpos, np.stack(reference))
    assert len(np.unique(qpos)) == qpos.size


def test_rest_energy_is_mujocos_mechanical_energy_at_zero_velocity(env):
    """Against MuJoCo's kinematics of the environment's model: g Σ m_b (height of body b's centre of mass above
    the shoulder)."""
    model = env.mj_model
    data = mujoco.MjData(model)
    qpos = np.random.default_rng(0).uniform(-np.pi, np.pi, (5, 2))
    for q, energy in zip(qpos, starts.rest_energy(env, qpos), strict=True):
        data.qpos[:], data.qvel[:] = q, 0.0
        mujoco.mj_kinematics(model, data)
        shoulder = data.xanchor[0, 2]  # the shoulder hinge's height
        reference = -model.opt.gravity[2] * model.body_mass @ (data.xipos[:, 2] - shoulder)
        assert energy == pytest.approx(reference, abs=1e-9)
    upright, hanging = starts.rest_energy(env, np.array([[0.0, 0.0], [np.pi, 0.0]]))
    assert upright == pytest.approx(-hanging) and 19 < upright < 20
    population = starts.population_energy(env, 4000)
    assert population.max() <= upright and abs(population.mean()) < 0.6  # uniform angles: mean ~0 (sd ~11)


def test_provenance_decides_whether_a_runs_starts_can_be_recomputed():
    """An entry's commit where git knows it; otherwise (a shallow clone, a commit of another repository) its start
    time against the change's."""
    unknown = {"commit": "f" * 40}
    assert provenance.plays_current_starts({"git": unknown, "time": "2026-12-01T00:00:00Z"})
    assert not provenance.plays_current_starts({"git": unknown, "time": "2026-11-28T00:00:00Z"})
    assert not provenance.plays_current_starts({"time": "2026-11-29T17:23:28Z"})
    assert provenance.plays_current_starts({"time": "2026-11-29T17:23:29Z"})
    for run in RUNS:
        provenance.check_current_starts(run)  # the committed GPU runs (code 0c4e564, 2026-12-05)


def test_policies_are_labelled_apart_when_their_folders_share_a_name():
    rows = [{"run": f"study/{agent}/clean-seeds2", "seed": seed, "source": "training evaluation 10",
             "energy": float(e), "return": 10.0 * e + seed} for agent in ("tdmpc2", "cfc-zp-det") for seed in (0, 1)
            for e in range(4)]
    fits = starts.policy_fits(rows, 0.0)
    assert [label for label, *_ in fits] == [f"{agent}/clean-seeds2 seed {seed}" for agent in ("tdmpc2", "cfc-zp-det")
                                            for seed in (0, 1)]
    assert [fit.adjusted for _, fit, *_ in fits] == pytest.approx([0.0, 1.0, 0.0, 1.0])
    alone = starts.policy_fits([{**r, "run": "study/tdmpc2/clean"} for r in rows[:4]], 0.0)
    assert alone[0][0] == "clean"  # one seed, a unique name: the folder's name alone


def test_adjusted_mean_against_least_squares_in_float64():
    rng = np.random.default_rng(1)
    energy = rng.uniform(-19, 19, 25)
    returns = 600 + 12 * energy + rng.normal(0, 50, 25)
    fit = starts.adjusted_mean(energy, returns, population_mean=1.5)
    design = np.stack([np.ones(25), energy], axis=1)
    coef, rss, *_ = np.linalg.lstsq(design, returns, rcond=None)
    s2 = rss[0] / (25 - 2)
    at = np.array([1.0, 1.5])
    assert fit.slope == pytest.approx(coef[1], rel=1e-12)
    assert fit.adjusted == pytest.approx(at @ coef, rel=1e-12)
    assert fit.stderr == pytest.approx(np.sqrt(s2 * at @ np.linalg.inv(design.T @ design) @ at), rel=1e-10)
    assert fit.r == pytest.approx(np.corrcoef(energy, returns)[0, 1], rel=1e-12)
    assert (fit.episodes, fit.mean, fit.energy_mean) == (25, pytest.approx(returns.mean()),
                                                         pytest.approx(energy.mean()))
    exact = starts.adjusted_mean(np.array([-2.0, 0.0, 4.0]), np.array([100.0, 120.0, 160.0]), 10.0)
    assert (exact.adjusted, exact.stderr, exact.r) == (pytest.approx(220.0), pytest.approx(0.0), pytest.approx(1.0))
    marked = np.arange(25) < 10
    shifted = np.where(marked, 30.0, 0.0) + 600 + 12 * energy
    assert starts.source_gap(energy, shifted, marked) == pytest.approx(30.0)
    noisy = shifted + rng.normal(0, 50, 25)
    design = np.stack([marked, ~marked, energy], axis=1).astype(float)
    coef = np.linalg.solve(design.T @ design, design.T @ noisy)  # the normal equations
    assert starts.source_gap(energy, noisy, marked) == pytest.approx(coef[0] - coef[1], rel=1e-10)
    assert np.isnan(starts.source_gap(energy, noisy, np.ones(25, bool)))
    with pytest.raises(ValueError, match="at least 3 episodes, got 2"):
        starts.adjusted_mean(np.zeros(2), np.zeros(2), 0.0)
    with pytest.raises(ValueError, match="same energy"):
        starts.adjusted_mean(np.ones(4), np.arange(4.0), 0.0)
    with pytest.raises(ValueError, match=r"equal 1-d arrays, got shapes \(3,\) and \(4,\)"):
        starts.adjusted_mean(np.zeros(3), np.zeros(4), 0.0)


def test_command_on_gpu_runs_finds_their_returns_following_the_starts_energy(tmp_path, capsys, monkeypatch):
    """The three committed runs' final training evaluations (GPU) and their policies' 20-episode MJX CSVs: every
    policy's logged returns correlate with the recomputed starts' energy (r > 0.8; starts from wrong keys would
    not), the CSV holds each episode once, bad input is refused with exit status 2, and without --out nothing is
    written."""
    extra = [f"{run}={RESULTS}/analysis/mjx-20ep-ar4-seed{seed}-200128.csv" for seed, run in enumerate(RUNS, 1)]
    out = str(tmp_path / "ar4")
    assert starts.main([*RUNS, "--with", *extra, "--population", "2000", "--out", out]) == 0
    table = capsys.readouterr().out
    with open(f"{out}.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 90 and len({(r["run"], r["source"], r["episode"]) for r in rows}) == 90
    assert os.path.getsize(f"{out}.png") > 10_000
    for run in RUNS:
        mine = [r for r in rows if r["run"] == run]
        energy, returns = (np.array([float(r[c]) for r in mine]) for c in ("energy", "return"))
        assert np.corrcoef(energy, returns)[0, 1] > 0.8
        trained = [float(r["return"]) for r in mine if r["source"] == "training evaluation 200128"]
        logged = [float(r["return"]) for r in csv.DictReader(open(os.path.join(run, "eval.csv")))
                  if r["env_step"] == "200128"]
        assert trained == logged
    assert table.count("| acrobot-recipe-ar4-seed") == 3 and "| mean of 3 | 90 |" in table
    assert "nan" not in table and " - |" not in table  # every policy has episodes of both kinds: a gap each

    def refused(*args):
        assert starts.main([*args, "--out", out]) == 2
        return capsys.readouterr().err

    assert f"--with takes RUN=CSV with RUN one of the runs given, got '{extra[1]}'" in refused(RUNS[0], "--with",
                                                                                              extra[1])
    assert "not at 100" in refused(RUNS[0], "--step", "100")
    assert "--population must be >= 2, got 1" in refused(RUNS[0], "--population", "1")
    plan5 = f"{RESULTS}/analysis/dm_control-ar4-seed3-200128-plan5.csv"  # a planner override, still clean
    assert starts.main([RUNS[2], "--with", f"{RUNS[2]}={plan5}", "--without-training", "--population", "2000",
                        "--out", out]) == 0
    assert "| acrobot-recipe-ar4-seed3 | 10 | - |" in capsys.readouterr().out  # no training evaluation fitted
    with open(f"{out}.csv", newline="") as f:
        assert {r["source"] for r in csv.DictReader(f)} == {os.path.basename(plan5)}
    empty = tmp_path / "cwd"
    empty.mkdir()
    monkeypatch.chdir(empty)  # without --out the table is printed and nothing written
    assert starts.main([RUNS[2], "--with", f"{RUNS[2]}={plan5}", "--without-training", "--population", "2000"]) == 0
    assert "| acrobot-recipe-ar4-seed3 | 10 | - |" in capsys.readouterr().out and os.listdir(empty) == []
    noisy = tmp_path / "noisy.csv"
    noisy.write_text(open(extra[0].split("=", 1)[1]).read().replace(",clean,", ",noise0.1,"))
    assert "only clean evaluations are supported (backend mjx or dm_control, obs clean), got backend 'mjx', obs " \
        "'noise0.1'" in refused(RUNS[0], "--with", f"{RUNS[0]}={noisy}")
    assert "--without-training leaves" in refused(RUNS[0], RUNS[1], "--with", extra[0], "--without-training")
    unseeded = tmp_path / "unseeded.csv"
    unseeded.write_text("".join(line.rsplit(",", 1)[0] + "\n" for line in open(extra[0].split("=", 1)[1])))
    assert "records no eval_seed" in refused(RUNS[0], "--with", f"{RUNS[0]}={unseeded}")
    old = tmp_path / "old"
    old.mkdir()
    saved = json.load(open(os.path.join(RUNS[0], "config.json")))
    (old / "eval.csv").write_text(open(os.path.join(RUNS[0], "eval.csv")).read())
    (old / "config.json").write_text(json.dumps({k: v for k, v in saved.items() if k != "provenance"}))
    assert "records no provenance: its evaluations drew their starts before 45dda0c" in refused(str(old))
    stale = {**saved["provenance"][0], "git": {"commit": "f" * 40}, "time": "2026-11-28T10:00:00Z"}
    (old / "config.json").write_text(json.dumps({**saved, "provenance": [*saved["provenance"], stale]}))
    assert "started at 2026-11-28T10:00:00Z" in refused(str(old))  # a resume with older code
    twice = tmp_path / "twice"
    twice.mkdir()
    (twice / "config.json").write_text(open(os.path.join(RUNS[0], "config.json")).read())
    logged = open(os.path.join(RUNS[0], "eval.csv")).read().splitlines()
    (twice / "eval.csv").write_text("\n".join([*logged, logged[-1]]) + "\n")  # the last episode logged again
    assert "holds an episode of the evaluation at 200128 twice" in refused(str(twice))
    walker = os.path.join(os.path.dirname(__file__), "..", "experiments", "results",
                          "cfc-walker-simnorm-latent512-200k-h200", "walker-simnorm-latent512-seed1")
    assert "trained walker-run; this analysis reads acrobot runs only" in refused(walker)
