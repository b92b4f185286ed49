"""Analysis scripts of ``experiments/scripts/``: ``episode_shares.py`` (the split of evaluation returns into the
initial state's share, the policy's and the rest, against sums of squares computed by hand in float64) and
``acrobot_hanging_starts.py``'s initial states, ``acrobot_oracle.py``'s mechanical energy (against MuJoCo's own,
C, float64), ``acrobot_ceiling_figure.py``'s join of per-start returns and ``program_hashes.py``'s lowered programs."""

import csv
import importlib.util
import os

import numpy as np
import pytest

ROOT = os.path.join(os.path.dirname(__file__), "..")


def _script(name: str = "episode_shares"):
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, "experiments", "scripts", f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _write(path, returns):  # as `cli eval` writes them
    path.write_text("env_step,seed,episode,return,backend,obs,actor,planner,eval_seed\n" + "".join(
        f"100,0,{e},{r},mjx,clean,planner,,0\n" for e, r in reversed(list(enumerate(returns)))))  # reordered
    return str(path)


def test_shares_split_an_additive_table_and_read_csvs_in_episode_order(tmp_path, capsys):
    script = _script()
    episode = np.array([700.0, 100.0, 400.0, 300.0])
    policy = np.array([0.0, 50.0, -20.0])
    table = policy[:, None] + episode[None, :]  # no interaction: the rest is zero
    split = script.shares(table)
    total = ((table - table.mean()) ** 2).sum()
    assert split["episode"] == pytest.approx(3 * ((episode - episode.mean()) ** 2).sum() / total)
    assert split["policy"] == pytest.approx(4 * ((policy - policy.mean()) ** 2).sum() / total)
    assert split["rest"] == pytest.approx(0.0, abs=1e-12)
    noisy = table + np.array([[5.0, -5.0, 0.0, 0.0], [-5.0, 5.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    assert script.shares(noisy)["rest"] > 0
    paths = [_write(tmp_path / f"p{i}.csv", row) for i, row in enumerate(table)]
    np.testing.assert_array_equal(script.returns_table(paths), table)
    assert script.main(paths) == 0
    out = capsys.readouterr().out
    assert out.startswith("3 policies x 4 episodes: episode share ") and "rest 0.00" in out
    assert "(mean 425.0)" in out.splitlines()[2]  # the best policy per episode: 750 150 450 350
    from lnnmpc.train.config import ConfigError

    with pytest.raises(ConfigError, match=r"hold other \(seed, episode\) rows: only in the first \[\(0, 3\)\]"):
        script.returns_table([paths[0], _write(tmp_path / "short.csv", [1.0, 2.0, 3.0])])
    assert script.main(paths[:1]) == 2


def test_hanging_starts_hang_at_rest_within_their_noise():
    import types

    import jax

    init = _script("acrobot_hanging_starts").hanging_init(0.1)
    fake_env = types.SimpleNamespace(mj_model=types.SimpleNamespace(nv=2))
    starts = [init(fake_env, key) for key in jax.random.split(jax.random.key(3), 64)]
    qpos = np.array([np.asarray(q) for q, _ in starts], np.float64)
    assert all(np.all(np.asarray(v) == 0) and np.shape(v) == (2,) for _, v in starts)  # at rest
    assert np.all((qpos >= -np.pi) & (qpos < np.pi))  # wrapped as dm_control's angles are drawn
    down = np.angle(np.exp(1j * (qpos[:, 0] - np.pi)))  # the shoulder's offset from straight down
    assert np.abs(down).max() < 0.5 and 0.05 < down.std() < 0.2 and np.any(qpos[:, 0] > 0) and np.any(qpos[:, 0] < 0)
    assert np.abs(qpos[:, 1]).max() < 0.5 and 0.05 < qpos[:, 1].std() < 0.2


def test_hanging_starts_time_an_agent_step_as_dm_control_times_a_control_step():
    from dm_control import suite

    from lnnmpc.envs.env import make

    control = suite.load("acrobot", "swingup", task_kwargs={"random": 0}).control_timestep()  # 0.01 s
    assert [make("acrobot-swingup", action_repeat=r).agent_timestep for r in (1, 2, 4)] == pytest.approx(
        [control, 2 * control, 4 * control])  # Env.agent_timestep, which the script's first_seconds_above uses


def test_oracle_energy_matches_mujoco_and_bad_arguments_are_refused(capsys):
    import copy

    import jax
    import jax.numpy as jnp
    import mujoco

    from lnnmpc.envs.env import make

    oracle = _script("acrobot_oracle")
    env = make("acrobot-swingup")
    model = copy.deepcopy(env.mj_model)  # MuJoCo computes energies only when asked to
    model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    data = mujoco.MjData(model)
    energy = oracle.state_energy(env)
    for qpos, qvel in [((np.pi, 0.0), (0.0, 0.0)), ((0.0, 0.0), (0.0, 0.0)), ((1.0, -0.5), (2.0, -3.0))]:
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(model, data)
        assert float(energy(jnp.asarray(qpos, jnp.float32), jnp.asarray(qvel, jnp.float32))) == pytest.approx(
            data.energy.sum(), rel=1e-4)
    down, up = oracle.energy_range(env)
    assert up - down == pytest.approx(2 * 9.81 * 2.0, rel=1e-3)  # two unit-mass links, centres 1 and 2 m apart
    starts = oracle.hanging_starts(16, 0.1, jax.random.key(0))
    assert starts.shape == (16, 2) and np.abs(np.angle(np.exp(1j * (starts[:, 0] - np.pi)))).max() < 0.5
    assert oracle.main(["--episodes", "0"]) == 2
    assert "--episodes and --chunk must be >= 1" in capsys.readouterr().err


def test_value_calibration_returns_to_go_and_summaries_against_direct_sums(capsys):
    script = _script("value_calibration")
    rng = np.random.default_rng(0)
    rewards = rng.uniform(0, 2, (3, 40))
    gamma = 0.9
    direct = np.array([[sum(gamma ** k * r[t + k] for k in range(40 - t)) for t in range(40)] for r in rewards])
    np.testing.assert_allclose(script.discounted_returns(rewards, gamma), direct, rtol=1e-12)
    np.testing.assert_array_equal(script.discounted_returns(rewards, 0.0), rewards)
    kept = script.uncut_steps(500, 0.99)
    last = kept - 1  # the last step kept: its return misses at most 5%, the next step's more
    assert 0.99 ** (500 - last) <= 0.05 < 0.99 ** (500 - last - 1) and kept == 202
    assert script.uncut_steps(10, 0.99) == 0
    assert script.uncut_steps(250, 0.99) == 0 and script.uncut_steps(250, 0.99, 0.1) == 21  # action repeat 4
    assert script.main(["no-such-run", "--tail", "1.5"]) == 2  # refused before the run is read
    assert "--tail must lie in (0, 1), got 1.5" in capsys.readouterr().err
    q = direct + 1.0
    keep = np.zeros_like(q, bool)
    keep[:, :5] = True
    summary = script.phase_summary(q, direct, keep)
    assert summary["steps"] == 15 and summary["bias"] == pytest.approx(1.0)
    assert summary["corr"] == pytest.approx(1.0) and summary["g"] == pytest.approx(direct[:, :5].mean())
    assert script.phase_summary(q, direct, np.zeros_like(keep))["steps"] == 0


def test_ceiling_figure_joins_sources_by_episode_with_the_starts_energy(tmp_path, capsys):
    script = _script("acrobot_ceiling_figure")
    planner = tmp_path / "planner.csv"
    planner.write_text("episode,return,start_shoulder,start_elbow\n9,300.0,0,0\n4,320.0,0,0\n")
    (tmp_path / "more.csv").write_text("episode,return,start_shoulder,start_elbow\n0,650.0,0,0\n")
    policy = _write(tmp_path / "policy.csv", [700.0, 1.0, 2.0, 3.0, 100.0])  # episodes 0-4, shares 0 and 4
    out = str(tmp_path / "fig")
    joined = f"P={planner}+{tmp_path / 'more.csv'}"
    assert script.main(["--planner", joined, "--policies", f"S={policy}", "--out", out]) == 0
    rows = list(csv.DictReader(open(f"{out}.csv")))
    assert [int(r["episode"]) for r in rows] == [0, 4]
    assert [float(r["best"]) for r in rows] == [700.0, 320.0]
    energies = [float(r["start_energy"]) for r in rows]
    assert -19.62 < energies[1] < -18.0 < energies[0] < 19.62  # episode 4 starts near hanging, within the range
    assert os.path.getsize(f"{out}.png") > 1000 and "P: 485.0" in capsys.readouterr().out
    assert script.main(["--planner", "no-label.csv", "--out", out]) == 2
    assert "LABEL=CSV" in capsys.readouterr().err


def test_program_hashes_tell_runs_apart_by_their_programs(tmp_path, capsys):
    """Lowered from config.json alone: another learning rate changes the training chunk and the update burst but
    not the seed phase or the evaluation (which never read it); the same settings under another master seed lower
    to the same text (the seed is a runtime key); a folder without config.json is refused."""
    from lnnmpc.train import runfolder
    from lnnmpc.train.config import TrainConfig

    script = _script("program_hashes")
    base = dict(task="cartpole-swingup", agent="tdmpc2", small=True, steps=400, seed_steps=200, eval_every=200,
                eval_episodes=2, compile_cache="")
    runs = []
    for name, extra in (("a", {}), ("b", {"seed": 3}), ("c", {"overrides": {"lr": 1e-3}})):
        (tmp_path / name).mkdir()
        runfolder.write_config(str(tmp_path / name), TrainConfig(**base, **extra, out=str(tmp_path / name)), {})
        runs.append(str(tmp_path / name))
    dump = tmp_path / "dump"
    assert script.main(runs + ["--dump", str(dump)]) == 0
    rows = capsys.readouterr().out.strip().splitlines()
    assert rows[-1] == "| all runs | differ | same | differ | same |"
    text = {(run, p): (dump / f"{run}-{p}.txt").read_text() for run in "abc" for p in script.PROGRAMS}
    assert all("func.func public @main" in t for t in text.values())
    assert text["a", "evaluate"] == text["c", "evaluate"] and text["a", "train_chunk"] != text["c", "train_chunk"]
    assert rows[2] == "| a | " + " | ".join(script.digest(text["a", p]) for p in script.PROGRAMS) + " |"
    assert rows[3] == rows[2].replace("| a |", "| b |")  # another master seed: the same programs
    assert script.main([str(tmp_path / "none")]) == 2 and "is not a run folder" in capsys.readouterr().err
    assert script.main(runs[:1] + ["--scatters"]) == 0
    counts = {p: script.scatter_counts(text["a", p]) for p in script.PROGRAMS}
    assert capsys.readouterr().out.strip().splitlines()[-1] == "| a | " + " | ".join(
        f"{counts[p]['adding']} / {counts[p]['other']}" for p in script.PROGRAMS) + " |"


def test_program_hashes_count_the_scatters_that_add_over_colliding_indices():
    """scatter_counts on three one-scatter programs: an add over indices that may repeat counts as adding; a set,
    and an add whose indices are declared unique, count as other."""
    import jax
    import jax.numpy as jnp

    script = _script("program_hashes")
    x, i, v = jnp.zeros(8), jnp.array([1, 1, 3]), jnp.ones(3)
    text = lambda f: jax.jit(f).lower(x, i, v).as_text()
    assert script.scatter_counts(text(lambda x, i, v: x.at[i].add(v))) == {"adding": 1, "other": 0}
    assert script.scatter_counts(text(lambda x, i, v: x.at[i].set(v))) == {"adding": 0, "other": 1}
    assert script.scatter_counts(text(lambda x, i, v: x.at[i].add(v, unique_indices=True))) == {"adding": 0, "other": 1}
    assert script.scatter_counts(text(lambda x, i, v: x + v.sum())) == {"adding": 0, "other": 0}


def test_acrobot_divergence_plays_each_start_twice_one_ulp_apart(tmp_path, capsys):
    """Two starts, 4 agent steps: the nudged play differs from the first agent step on (one ulp of a joint angle
    shows in the observation) by amounts of round-off's order; the CSV holds one row per agent step; bad sizes are
    refused naming the flag; first_above finds the first step over a level (1-based) or None."""
    script = _script("acrobot_divergence")
    gaps = script.divergence(starts=2, agent_steps=4, action_repeat=2)
    assert gaps.shape == (2, 4) and np.all(gaps[:, 0] > 0) and np.all(gaps < 1e-3)
    out = str(tmp_path / "div")
    assert script.main(["--starts", "2", "--agent-steps", "4", "--action-repeat", "2", "--out", out]) == 0
    rows = list(csv.DictReader(open(f"{out}.csv")))
    assert [int(r["agent_step"]) for r in rows] == [1, 2, 3, 4]
    assert np.allclose([float(r["max"]) for r in rows], gaps.max(axis=0), rtol=1e-5)
    printed = capsys.readouterr().out
    assert os.path.getsize(f"{out}.png") > 1000 and "median above 0.001 from agent step never" in printed
    assert script.main(["--starts", "0"]) == 2 and "--starts must be at least 1, not 0" in capsys.readouterr().err
    assert script.first_above(np.array([0.0, 1e-4, 0.2, 0.5]), 1e-3) == 3
    assert script.first_above(np.array([0.0, 1e-4]), 1e-3) is None


def test_final_returns_figure_takes_each_runs_last_evaluation_by_line(tmp_path, capsys):
    """Each run's value is the mean over seeds and episodes of its last evaluation (not of all rows), lines keep
    their order and their runs' positions; malformed or repeated lines, bad references and a folder without
    eval.csv are refused naming the item (exit status 2)."""
    script = _script("final_returns_figure")
    rows = lambda step, returns: "".join(f"{step},{s},{e},{r}\n" for s, seed in enumerate(returns)
                                         for e, r in enumerate(seed))
    runs = {}
    for name, last in (("a1", [[100.0, 300.0]]), ("a2", [[500.0], [700.0]]), ("b1", [[50.0, 60.0]])):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "eval.csv").write_text("env_step,seed,episode,return\n" + rows(10, [[999.0]]) + rows(20, last))
        runs[name] = str(folder)
    out = str(tmp_path / "fig")
    argv = ["--line", f"second={runs['b1']}", "--line", f"first={runs['a1']},{runs['a2']}", "--bar", "700",
            "--reference", "TD-MPC2=278.1", "--run-names", "s1,s2", "--out", out]
    assert script.main(argv) == 0
    table = list(csv.DictReader(open(f"{out}.csv")))
    assert [(r["line"], r["position"], r["env_step"], float(r["return"]), float(r["line_mean"])) for r in table] == [
        ("second", "0", "20", 55.0, 55.0), ("first", "0", "20", 200.0, 400.0), ("first", "1", "20", 600.0, 400.0)]
    printed = capsys.readouterr().out
    assert "first: 200.0 / 600.0, mean 400.0" in printed and os.path.getsize(f"{out}.png") > 1000
    assert script.run_name(1, ["s1", "s2"]) == "s2" and script.run_name(2, ["s1", "s2"]) == "run 3 of each line"
    for bad, message in (([f"--line=x{runs['a1']}"], "--line takes LABEL=RUN[,RUN...], got 'x"),
                         (["--line", f"x={runs['a1']}", "--line", f"x={runs['a2']}"], "--line 'x' given twice"),
                         (["--line", f"x={tmp_path}"], "has no eval.csv"),
                         (["--line", f"x={runs['a1']}", "--reference", "TD=high"], "--reference takes LABEL=VALUE")):
        assert script.main([*bad, "--out", out]) == 2 and message in capsys.readouterr().err


def test_the_acrobot_levers_figure_regenerates_from_the_committed_runs(tmp_path):
    """experiments/scripts/acrobot_levers_figure.sh rebuilds the committed figure's CSV byte for byte from the
    committed runs (their eval.csv), so the figure states what the runs hold (RESULTS.md [102]: the recipe, gamma
    0.985, launched again 646.5; [104]: with the latent head's observation skip 641.3; [106]: with a CfC backbone 256
    wide 664.5, launched again 638.0 [107]; [108]: 512 wide 647.9; [109]: 512 windows per update 624.3; [110]: MPPI
    with 12 iterations while training 636.2; [112]: exploring with at least 0.2 / 0.5 x the noise 656.9 / 595.1)."""
    import subprocess
    import sys

    committed = os.path.join(ROOT, "experiments", "results", "figures", "acrobot-levers-master-seeds123-200k.csv")
    env = {**os.environ, "PYTHON": sys.executable, "PYTHONPATH": os.path.join(ROOT, "src")}
    done = subprocess.run(["bash", "experiments/scripts/acrobot_levers_figure.sh", str(tmp_path / "fig")], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert open(tmp_path / "fig.csv").read() == open(committed).read()
    assert "every 6, gamma 0.985 again (recipe) [102]: 675.0 / 621.2 / 643.2, mean 646.5" in done.stdout
    assert "every 6, gamma 0.985, observation skip [104]: 610.6 / 626.0 / 687.4, mean 641.3" in done.stdout
    assert "every 6, gamma 0.985, tau 0.02 [105]: 619.5 / 634.8 / 634.1, mean 629.5" in done.stdout
    assert "every 6, gamma 0.985, CfC backbone 256 [106]: 639.4 / 655.2 / 698.8, mean 664.5" in done.stdout
    assert "every 6, gamma 0.985, CfC backbone 256 again [107]: 623.2 / 636.3 / 654.4, mean 638.0" in done.stdout
    assert "every 6, gamma 0.985, CfC backbone 512 [108]: 621.6 / 637.9 / 684.3, mean 647.9" in done.stdout
    assert "every 6, gamma 0.985, 512 windows/update [109]: 620.2 / 629.6 / 623.2, mean 624.3" in done.stdout
    assert "every 6, gamma 0.985, MPPI 12 iterations [110]: 616.7 / 631.8 / 660.0, mean 636.2" in done.stdout
    assert "every 6, gamma 0.985, exploration floor 0.2 [112]: 639.8 / 621.2 / 709.7, mean 656.9" in done.stdout
    assert "every 6, gamma 0.985, exploration floor 0.5 [112]: 542.5 / 610.1 / 632.6, mean 595.1" in done.stdout
