"""Representation analyses: float64 references on synthetic data, known matrices, a toy model; the report on a
checkpoint of an untrained small OP agent (short episodes, no UMAP) through the JAX glue."""

import csv
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.analysis import acrobot, cartpole, metrics, report
from lnnmpc.analysis.projection import log_speed
from lnnmpc.analysis.rollout import rollout_program
from lnnmpc.train import runfolder
from lnnmpc.train.checkpoint import save_checkpoint
from lnnmpc.train.compat import state_signature
from lnnmpc.train.config import TrainConfig
from lnnmpc.train.setup import build_loop


def test_ridge_matches_an_independent_float64_solution_and_recovers_a_quadratic_state():
    rng = np.random.default_rng(0)
    z = rng.normal(size=(400, 6))
    x = metrics.quadratic_features(z)
    states = np.stack([2 * z[:, 0] - z[:, 3] ** 2, z[:, 2] ** 2 + 3.0], axis=1)
    alpha = 2.5
    w, b = metrics.ridge_fit(x, states, alpha)
    xc, yc = x - x.mean(0), states - states.mean(0)  # reference: least squares on the augmented system
    a = np.vstack([xc, np.sqrt(alpha) * np.eye(x.shape[1])])
    w_ref = np.linalg.lstsq(a, np.vstack([yc, np.zeros((x.shape[1], 2))]), rcond=None)[0]
    np.testing.assert_allclose(w, w_ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(b, states.mean(0) - x.mean(0) @ w_ref, atol=1e-10)
    r, predicted = metrics.ridge_pearson(z, states, alpha=1e-6)
    np.testing.assert_allclose(r, 1.0, atol=1e-9)
    np.testing.assert_allclose(predicted, states, atol=1e-5)
    noise = metrics.ridge_pearson(z, rng.normal(size=(400, 1)))[0]
    assert abs(noise[0]) < 0.3


def test_pearson_matches_numpy_and_is_nan_for_a_constant_column():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    expected = [np.corrcoef(a[:, i], b[:, i])[0, 1] for i in range(3)]
    np.testing.assert_allclose(metrics.pearson(a, b), expected, rtol=1e-12)
    assert np.isnan(metrics.pearson(np.ones((5, 1)), np.arange(5.0)[:, None])[0])


def test_effective_rank_of_known_matrices():
    rng = np.random.default_rng(2)
    assert metrics.effective_rank(np.outer(rng.normal(size=30), rng.normal(size=8))) == pytest.approx(1.0, abs=1e-9)
    assert metrics.effective_rank(np.eye(5)) == pytest.approx(5.0)
    assert metrics.effective_rank(np.diag([3.0, 1.0])) == pytest.approx(np.exp(-(0.75 * np.log(0.75)
                                                                                + 0.25 * np.log(0.25))))
    with pytest.raises(ValueError, match="non-zero"):
        metrics.effective_rank(np.zeros((3, 3)))


def test_device_effective_rank_matches_the_float64_reference():
    from lnnmpc.train.loop import effective_rank

    rng = np.random.default_rng(5)
    batch = np.stack([rng.normal(size=(40, 6)), np.outer(rng.normal(size=40), rng.normal(size=6)),
                      rng.normal(size=(40, 6)) * np.array([5.0, 1.0, 0.1, 0.0, 0.0, 2.0])])
    got = np.asarray(effective_rank(jnp.asarray(batch, jnp.float32)))
    np.testing.assert_allclose(got, [metrics.effective_rank(z) for z in batch], rtol=2e-3)
    assert got.shape == (3,) and got[1] == pytest.approx(1.0, abs=2e-3)


def test_evaluation_logs_each_episodes_effective_rank_as_the_analysis_computes_it():
    """The trainer's evaluation program returns, per episode, the return and the effective rank of the latents
    it planned from; the analysis rollout of the same key plays the same episodes (float64 NumPy rank)."""
    import dataclasses

    from lnn_helpers import quick_jit, tiny_agent

    from lnnmpc import envs
    from lnnmpc.analysis.rollout import rollout
    from lnnmpc.train.loop import LoopConfig, TrainingLoop

    env = envs.make("cartpole-swingup")
    short = dataclasses.replace(env, spec=dataclasses.replace(env.spec, control_steps=60))  # 30 agent steps
    agent = tiny_agent("cfc-op-det", env.observation_size, env.action_size)
    loop = TrainingLoop(agent, env, short, LoopConfig(batch_size=8, replay_capacity=64, eval_episodes=3))
    state, key = agent.init(jax.random.key(3)), jax.random.key(4)
    returns, ranks = (np.asarray(x) for x in quick_jit(loop.evaluate_with_rank)(state, key))
    calls = []
    rec = rollout(agent, state, short, key, 3, progress=lambda done, total: calls.append((done, total)))
    assert rec["latent"].shape == (3, 30, agent.config.model.hidden_size)
    # progress from inside the compiled scan: agent steps done, rising, through the last of the 30
    assert calls[-1] == (30, 30) and [d for d, _ in calls] == sorted({d for d, _ in calls}) and len(calls) > 1
    np.testing.assert_allclose(returns, rec["reward"].sum(axis=1), rtol=1e-5)
    np.testing.assert_allclose(ranks, [metrics.effective_rank(z) for z in rec["latent"]], rtol=2e-3)
    assert np.all((ranks >= 1) & (ranks <= agent.config.model.hidden_size))


def test_k_step_errors_of_a_biased_toy_model_accumulate_the_bias():
    """True o_{t+1} = o_t + a_t; the model adds a bias b each step, so the j-th step is off by j·b."""
    T, bias = 40, 0.1
    actions = np.sin(np.arange(T))[:, None]
    obs = np.concatenate([[[0.0]], np.cumsum(actions, axis=0)[:-1]])
    model = lambda z, a: z + a + bias
    errors = metrics.k_step_errors(model, model, obs, actions, obs, k=10)
    assert errors.shape == (T - 10, 10)
    np.testing.assert_allclose(errors, np.broadcast_to(((np.arange(1, 11) * bias) ** 2), errors.shape), atol=1e-12)
    exact = lambda z, a: z + a
    assert np.abs(metrics.k_step_errors(exact, exact, obs, actions, obs, k=3, stride=5)).max() < 1e-12
    rows = report.prediction_rows(np.stack([errors, 2 * errors]), 10)
    assert rows[0] == {"metric": "one-step", "mean": pytest.approx(1.5 * bias**2), "std": pytest.approx(0.5 * bias**2),
                       "episodes": 2}


def test_cartpole_phase_split():
    angle = np.concatenate([np.linspace(np.pi, 0.5, 60), np.full(10, 0.1), [0.5], np.full(40, -0.05)])
    assert metrics.balance_start(angle, threshold=0.3, hold=25) == 71  # the short upright run is too short
    assert metrics.balance_start(np.full(30, 3.0)) == 30
    assert metrics.balance_start(np.full(30, 2 * np.pi + 0.1), hold=5) == 0  # wrapped
    masks = report.phase_masks("cartpole-swingup", np.stack([np.zeros(30), np.r_[np.full(10, 3.0), np.zeros(20)]],
                                                            axis=-1)[None], hold=5)
    assert masks["swingup"][0].sum() == 10 and masks["balance"][0, 10:].all()
    assert list(report.phase_masks("walker-run", np.zeros((2, 7, 9)))) == ["all"]
    np.testing.assert_allclose(log_speed(np.array([-1.0, 0.0])), [np.log(1.001), np.log(1e-3)])


def test_observation_names_follow_the_kept_dimensions():
    from lnnmpc import envs

    names = report.STATE_NAMES["cartpole"]
    no_velocity = envs.make("cartpole-swingup", remove_vel=True)
    assert report.observation_names(names, no_velocity.kept, 3) == ("cart position", "pole cos", "pole sin")
    assert report.observation_names(names, envs.make("cartpole-swingup").kept, 5) == names
    assert report.observation_names(names, no_velocity.kept, 5) == ()  # sizes disagree: no names
    assert report.observation_names(("a",), no_velocity.kept, 3) == ()


def _untrained_run(path) -> str:
    """A run folder holding two checkpoints (steps 0 and 500) of untrained small cfc-op-det agents with different
    initial parameters (no training needed)."""
    config = TrainConfig(task="cartpole-swingup", agent="cfc-op-det", obs="remove_vel=1", small=True, seeds=1,
                         steps=1000, seed_steps=0, replay_capacity=64, out=str(path), compile_cache="")
    loop = build_loop(config)
    os.makedirs(path)
    runfolder.write_config(str(path), config, {"state_signature": state_signature(loop, 1)})
    keys = jax.random.split(jax.random.key(0), 1)
    key_shape = jax.random.key_data(keys).shape[1:]  # zeros for all but the agent: only the agent is analysed
    zeros = jax.tree_util.tree_map(lambda x: jax.random.wrap_key_data(jnp.zeros(x.shape + key_shape, jnp.uint32))
                                   if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else jnp.zeros(x.shape, x.dtype),
                                   jax.eval_shape(jax.vmap(loop.init), keys))
    for step in (0, 500):
        agent = jax.jit(jax.vmap(loop.agent.init))(jax.random.split(jax.random.key(step), 1))
        save_checkpoint(str(path), step, zeros.replace(agent=agent), {"env_steps": step})
    return str(path)


def test_report_on_a_checkpoint_writes_every_analysis(tmp_path):
    run = _untrained_run(tmp_path / "run")
    compiled = rollout_program.cache_info().misses
    out = report.analyse(run, episodes=2, length=40, use_umap=False)
    assert out == os.path.join(run, "analysis", "500")
    assert rollout_program.cache_info().misses == compiled + 1  # one rollout program for both checkpoints
    assert sorted(os.listdir(out)) == ["correlation-swingup.png", "correlation.csv", "effective_rank.csv",
                                       "effective_rank.png", "prediction.png", "prediction_error.csv"]
    with open(os.path.join(out, "correlation.csv")) as f:
        rows = list(csv.DictReader(f))
    assert [r["variable"] for r in rows] == list(report.STATE_NAMES["cartpole"])
    assert {r["phase"] for r in rows} == {"swingup"} and rows[0]["samples"] == "80"
    with open(os.path.join(out, "prediction_error.csv")) as f:
        errors = list(csv.DictReader(f))
    assert [r["metric"] for r in errors] == ["one-step", "step 10", "mean over 10 steps"]
    assert all(np.isfinite(float(r["mean"])) and r["episodes"] == "2" for r in errors)
    with open(os.path.join(out, "effective_rank.csv")) as f:
        ranks = list(csv.DictReader(f))
    assert [r["env_step"] for r in ranks] == ["0", "500"]
    assert all(1.0 <= float(r["effective_rank"]) <= 16 for r in ranks)
    assert ranks[0]["effective_rank"] != ranks[1]["effective_rank"]  # each checkpoint's own parameters
    # A run whose trainer logged the evaluations' ranks: the report takes them from eval.csv, rolls out nothing more
    runfolder.write_csv(os.path.join(run, "eval.csv"), ["env_step", "seed", "episode", "return", "effective_rank"],
                        [{"env_step": step, "seed": 0, "episode": e, "return": 1.0, "effective_rank": step / 100 + e}
                         for step in (100, 300, 500) for e in (0, 1)])
    compiled = rollout_program.cache_info().misses
    hits = rollout_program.cache_info().hits
    out = report.analyse(run, episodes=2, length=40, use_umap=False)
    # one rollout, of the newest checkpoint, no other checkpoint's: a new policy object of the same agent
    # configuration and environment, so the program compiled above (one hit, no miss)
    assert rollout_program.cache_info().misses == compiled and rollout_program.cache_info().hits == hits + 1
    with open(os.path.join(out, "effective_rank.csv")) as f:
        ranks = list(csv.DictReader(f))
    assert [(r["env_step"], float(r["effective_rank"]), float(r["std"])) for r in ranks] == [
        ("100", 1.5, 0.5), ("300", 3.5, 0.5), ("500", 5.5, 0.5)]


def test_cartpole_episode_stats_of_known_trajectories():
    T = 2000
    t = np.arange(T) / T
    held = np.stack([np.full(T, 0.1), np.zeros(T)], axis=-1)  # balanced at the centre from the start
    spin = 3 * 2 * np.pi * t
    spinning = np.stack([np.full(T, 0.5), np.angle(np.exp(1j * (np.pi + spin)))], axis=-1)  # wrapped, off centre
    swing = np.stack([np.full(T, -0.3), np.pi * np.clip(1 - 2 * t, 0, 1)], axis=-1)  # down to up, then held
    stats = cartpole.episode_stats(np.stack([held, spinning, swing]))
    np.testing.assert_allclose(stats["turns"], [0.0, 3 * (T - 1) / T, 0.5], atol=1e-9)
    arc = np.arccos(0.995) / np.pi  # the upright arc's share of one turn at a constant rate
    np.testing.assert_allclose(stats["upright_share"], [1.0, arc, 0.5 + arc / 2], atol=2e-3)
    np.testing.assert_allclose(stats["sparse_region_share"], [1.0, 0.0, 0.0])  # the cart at 0.5 and -0.3: outside
    np.testing.assert_allclose(stats["mean_abs_cart"], [0.1, 0.5, 0.3])
    with pytest.raises(ValueError, match=r"\(episodes, steps, 2\)"):
        cartpole.episode_stats(np.zeros((4, 2)))


def test_cartpole_analysis_reports_every_seed_and_refuses_other_tasks(tmp_path, capsys):
    """(2 episodes of 40 agent steps: the rollout program the report's test above compiled, reused in the same
    process)"""
    run = _untrained_run(tmp_path / "run")
    assert cartpole.main([run, "--episodes", "2", "--length", "40"]) == 0
    with open(os.path.join(run, "analysis", "500", "cartpole_episodes.csv")) as f:
        rows = list(csv.DictReader(f))
    with open(os.path.join(run, "analysis", "500", "cartpole_episodes.png"), "rb") as f:  # the episodes over time
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    cos, cart = cartpole.episode_traces(np.array([[[0.1, 0.0], [-0.3, np.pi]]]))
    np.testing.assert_allclose(cos.values, [[1.0, -1.0]])
    np.testing.assert_allclose(cart.values, [[0.1, -0.3]])
    assert cos.band == (0.995, 1.0) and cart.band == (-0.25, 0.25)
    assert [(r["env_step"], r["seed"], r["episodes"]) for r in rows] == [("500", "0", "2")]
    row = {k: float(rows[0][k]) for k in ("return", *cartpole.STATS)}
    assert 0 <= row["return"] <= 40 and row["turns"] > 0  # an untrained agent moves the pole, rarely up
    assert 0 <= row["sparse_region_share"] <= row["upright_share"] <= 1 and row["mean_abs_cart"] >= 0
    out, err = capsys.readouterr()
    assert "| seed | return | turns |" in out
    assert "] 40/40 agent steps (2 episode(s) per seed, one seed after another, MJX)" in err  # the progress line
    assert err.endswith(", done\n")
    other = _config_only_run(tmp_path / "acrobot", "acrobot-swingup")
    assert cartpole.main([other]) == 2
    assert "trained on acrobot-swingup" in capsys.readouterr().err
    assert cartpole.main([run, "--episodes", "0"]) == 2


def test_acrobot_tip_from_mujoco_matches_the_links_geometry():
    """MuJoCo's kinematics of dm_control's acrobot against the two unit links hinged at the shoulder, z = 2 (float64
    numpy): the tip at (sin q1 + sin(q1 + q2), 2 + cos q1 + cos(q1 + q2)) up to the x axis's sign; target (0, 4)."""
    qpos = np.random.default_rng(0).uniform(-np.pi, np.pi, (3, 7, 2))
    tips, shoulder, target, radius = acrobot.tip_positions(qpos)
    q1, q12 = qpos[..., 0], qpos.sum(-1)
    np.testing.assert_allclose(tips[..., 2], 2 + np.cos(q1) + np.cos(q12), atol=1e-12)
    np.testing.assert_allclose(np.abs(tips[..., 0]), np.abs(np.sin(q1) + np.sin(q12)), atol=1e-12)
    np.testing.assert_allclose(tips[..., 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(shoulder, [0, 0, 2])
    np.testing.assert_allclose(target, [0, 0, 4])
    assert radius == pytest.approx(0.2)


def test_acrobot_episode_stats_of_known_trajectories(tmp_path, capsys):
    T = 1200
    t = np.arange(T) / T
    upright = np.zeros((T, 2))
    hanging = np.tile([np.pi, 0.0], (T, 1))
    whirl = np.stack([np.angle(np.exp(1j * (np.pi + 3 * 2 * np.pi * t))), np.zeros(T)], axis=-1)  # wrapped
    swing_then_balance = np.where(t[:, None] < 0.5, hanging, upright)
    stats = acrobot.episode_stats(np.stack([upright, hanging, whirl, swing_then_balance]))
    np.testing.assert_allclose(stats["shoulder_turns"], [0, 0, 3 * (T - 1) / T, 0.5], atol=1e-9)
    np.testing.assert_allclose(stats["elbow_turns"], 0.0, atol=1e-12)
    arc = 2 * np.arcsin(0.05) / np.pi  # the outstretched tip within 0.2 of the target: 4 |sin(θ / 2)| <= 0.2
    np.testing.assert_allclose(stats["target_share"], [1, 0, arc, 0.5], atol=2e-3)
    np.testing.assert_allclose(stats["longest_target_stay"], [1, 0, arc / 3, 0.5], atol=2e-3)  # one pass a turn
    # the whirl (3 turns from hanging) first enters the target half a turn less half the arc in: t = (1/2 - arc/2) / 3
    np.testing.assert_allclose(stats["before_target_share"], [0, 1, (0.5 - arc / 2) / 3, 0.5], atol=2e-3)
    np.testing.assert_allclose(stats["tip_above_share"], [1, 0, 0.5, 0.5], atol=2e-3)
    np.testing.assert_allclose(stats["mean_tip_distance"][[0, 1, 3]], [0, 4, 2], atol=1e-9)
    # eq. 4.6 pays hanging as upright; over a whirl's turns 0.5 |cos| averages 1 / π, the still elbow adds 0.5
    np.testing.assert_allclose(stats["thesis_reward_mean"], [1, 1, 0.5 + 1 / np.pi, 1], atol=2e-3)
    np.testing.assert_array_equal(acrobot.longest_stay(np.array([[1, 1, 0, 1, 1, 1, 0], [0] * 7], bool)), [3, 0])
    height, distance = acrobot.episode_traces(np.stack([upright, hanging, swing_then_balance]))  # the figure's
    assert height.band == pytest.approx((1.8, 2.2)) and distance.band == pytest.approx((0.0, 0.2))
    np.testing.assert_allclose(height.values[:, [0, -1]], [[2, 2], [-2, -2], [-2, 2]], atol=1e-12)
    np.testing.assert_allclose(distance.values[:, [0, -1]], [[0, 0], [4, 4], [4, 0]], atol=1e-12)
    with pytest.raises(ValueError, match=r"\(episodes, steps, 2\) = \[shoulder angle, elbow angle\]"):
        acrobot.episode_stats(np.zeros((5, 2)))
    other = _config_only_run(tmp_path / "cartpole", "cartpole-swingup")
    assert acrobot.main([other]) == 2
    assert "trained on cartpole-swingup: this analysis reads acrobot's joints" in capsys.readouterr().err
    assert acrobot.main([other, "--length", "1"]) == 2


def _config_only_run(folder, task: str) -> str:
    """A run folder of ``task`` with its config.json only (what the analyses read before they roll out)."""
    os.makedirs(folder)
    runfolder.write_config(str(folder), TrainConfig(task=task, agent="cfc-zp-det", small=True, out=str(folder),
                                                    compile_cache=""), {})
    return str(folder)


def _rank_run(folder, rows, rank_column=True, model=None):
    """A results folder as the trainer leaves it, minus checkpoints: config.json and eval.csv only."""
    import json

    os.makedirs(folder)
    with open(os.path.join(folder, "config.json"), "w") as f:
        json.dump({"config": {"task": "cartpole-swingup", "agent": "cfc-zp-det"},
                   "agent_config": {"model": model or {"hidden_size": 16, "latent_size": 0}}}, f)
    fields = ["env_step", "seed", "episode", "return"] + (["effective_rank"] if rank_column else [])
    with open(os.path.join(folder, "eval.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def test_ranks_only_report_pools_seeds_from_eval_csv_without_a_checkpoint(tmp_path):
    rng = np.random.default_rng(5)
    rows = [{"env_step": step, "seed": seed, "episode": ep, "return": 1.0, "effective_rank": rng.uniform(1, 16)}
            for step in (10_000, 20_000) for seed in range(3) for ep in range(4)]
    run = str(tmp_path / "run")
    _rank_run(run, rows)
    assert report.main([run, "--ranks-only"]) == 0
    got = list(csv.DictReader(open(os.path.join(run, "analysis", "effective_rank.csv"))))
    assert [int(r["env_step"]) for r in got] == [10_000, 20_000]
    for r in got:
        values = np.array([row["effective_rank"] for row in rows if row["env_step"] == int(r["env_step"])])
        assert int(r["episodes"]) == 12 and int(r["latent_dim"]) == 16
        np.testing.assert_allclose([float(r["effective_rank"]), float(r["std"])], [values.mean(), values.std()],
                                   rtol=1e-6)
    assert os.path.getsize(os.path.join(run, "analysis", "effective_rank.png")) > 0
    out = str(tmp_path / "seed1")
    assert report.main([run, "--ranks-only", "--seed-index", "1", "--out", out]) == 0
    one = list(csv.DictReader(open(os.path.join(out, "effective_rank.csv"))))
    seed1 = [row["effective_rank"] for row in rows if row["seed"] == 1 and row["env_step"] == 10_000]
    assert int(one[0]["episodes"]) == 4
    np.testing.assert_allclose(float(one[0]["effective_rank"]), np.mean(seed1), rtol=1e-6)
    # A SimNorm head 48 wide on the 16-unit state: the ranks are of its 48-dim latents.
    wide = str(tmp_path / "wide")
    _rank_run(wide, rows, model={"hidden_size": 16, "latent_head": "simnorm", "latent_size": 48})
    assert report.main([wide, "--ranks-only"]) == 0
    got = list(csv.DictReader(open(os.path.join(wide, "analysis", "effective_rank.csv"))))
    assert {int(r["latent_dim"]) for r in got} == {48}


def test_ranks_only_report_names_a_run_without_logged_ranks(tmp_path, capsys):
    run = str(tmp_path / "old")
    _rank_run(run, [{"env_step": 10_000, "seed": 0, "episode": 0, "return": 3.0}], rank_column=False)
    assert report.main([run, "--ranks-only"]) != 0
    assert "no effective_rank column" in capsys.readouterr().err
