"""``lnnmpc.analysis.plan_std``: the planner's final std recorded while an agent acts, without changing how it acts."""

from __future__ import annotations

import csv

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lnn_helpers import LinearEnv, perturbed_state, quick_jit

from lnnmpc.agents.mppi import mppi_plan
from lnnmpc.agents.registry import make_agent
from lnnmpc.analysis import plan_std
from lnnmpc.train.config import ConfigError
from lnnmpc.train.loop import play_episodes

OBS_DIM, ACT_DIM = LinearEnv.observation_size, LinearEnv.action_size


@pytest.mark.parametrize("name", ["tdmpc2", "cfc-zp-det"])
def test_recording_acts_as_the_agent_and_reports_the_first_planned_std(name):
    agent = make_agent(name, OBS_DIM, ACT_DIM, small=True)
    state = perturbed_state(agent, jax.random.key(0))
    recording = plan_std.StdRecording(agent)
    act = quick_jit(lambda c, o, k, f: agent.act(state, c, o, jnp.asarray(1.0), k, explore=False, first_step=f))
    record = quick_jit(lambda c, o, k, f: recording.act(state, c, o, jnp.asarray(1.0), k, explore=False,
                                                        first_step=f))
    obs = jax.random.normal(jax.random.key(2), (2, OBS_DIM))
    carry, wrapped = agent.initial_carry(), recording.initial_carry()
    planner = agent.config.planner
    for t in range(2):  # two steps: an LNN agent's carry matters in the second
        first, key = jnp.asarray(t == 0), jax.random.key(10 + t)
        action, carry = act(carry, obs[t], key, first)
        same, wrapped = record(wrapped, obs[t], key, first)
        np.testing.assert_allclose(same, action, rtol=1e-6, atol=1e-7)
        for a, b in zip(jax.tree_util.tree_leaves(wrapped[0]), jax.tree_util.tree_leaves(carry), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
        assert planner.min_std <= float(wrapped[1]) <= planner.max_std
        elites = np.asarray(wrapped[2])
        assert elites.shape == (planner.num_elites,) and np.all(np.diff(elites) <= 0)  # top-k values, best first
    if name == "tdmpc2":  # the same search run by hand from the encoded observation and the first step's plan mean
        z = agent._apply(state.params, obs[1], method="encode")
        by_hand = quick_jit(lambda z, prev, k: mppi_plan(planner, agent.planning_model(state.params), z, prev, k,
                                                         explore=False, first_step=jnp.asarray(False))[2])
        first_mean = act(agent.initial_carry(), obs[0], jax.random.key(10), jnp.asarray(True))[1]
        info = by_hand(z, first_mean, jax.random.key(11))
        np.testing.assert_allclose(float(wrapped[1]), np.asarray(info["std"])[0].mean(), rtol=1e-5)
        np.testing.assert_allclose(wrapped[2], info["elite_values"], rtol=1e-5)
        assert float(info["elite_values"][0]) == pytest.approx(float(info["elite_value_max"]))


def test_recorded_episodes_return_what_play_episodes_returns():
    env = LinearEnv()
    agent = make_agent("cfc-zp-det", OBS_DIM, ACT_DIM, small=True)
    state = perturbed_state(agent, jax.random.key(3))
    calls = []
    returns, std, reward, elites = plan_std.plan_std_episodes(
        agent, state, env, jax.random.key(4), episodes=2, progress=lambda done, total: calls.append((done, total)))
    # progress from inside the compiled scan: agent steps done, rising, through the last of the 4
    assert calls[-1] == (4, 4) and [d for d, _ in calls] == sorted({d for d, _ in calls})
    plain, _ = quick_jit(lambda s, k: play_episodes(agent, s, env, k, 2))(state, jax.random.key(4))
    assert std.shape == reward.shape == (4, 2) and elites.shape == (4, 2, agent.config.planner.num_elites)
    assert np.all(np.diff(elites, axis=-1) <= 0) and np.ptp(elites) > 0
    np.testing.assert_allclose(returns, np.asarray(plain), rtol=1e-5)
    np.testing.assert_allclose(reward.sum(axis=0), returns, rtol=1e-5)
    assert np.all((std >= agent.config.planner.min_std) & (std <= agent.config.planner.max_std))
    assert np.ptp(std) > 0  # the std moves with the state: recorded per step, not one constant


def test_summary_and_option_checks():
    summary = plan_std.std_summary(np.array([[0.1, 0.3], [0.6, 1.0]]), (0.2, 0.5))
    assert summary == pytest.approx({"p10": 0.16, "p50": 0.45, "p90": 0.88, "under_0.2": 0.25, "under_0.5": 0.5})
    with pytest.raises(ValueError, match="no std values"):
        plan_std.std_summary(np.array([]), (0.2,))
    assert plan_std.parse_positive_numbers("0.2,0.5", "--floors") == (0.2, 0.5)
    for bad in ("", "0.2,x", "-1", "0", "nan"):
        with pytest.raises(ConfigError, match="--temperatures takes positive numbers separated by commas"):
            plan_std.parse_positive_numbers(bad, "--temperatures")
    with pytest.raises(ValueError, match="object does not plan with MPPI"):
        plan_std.StdRecording(object())


def test_effective_elites_counts_the_elites_that_share_the_weight():
    values = np.array([[3.0, 3.0, 3.0, 3.0],  # alike: all four
                       [5.0, 5.0, -1e4, -1e4],  # two far ahead: two
                       [9.0, -1e4, -1e4, -1e4]])  # one: one
    np.testing.assert_allclose(plan_std.effective_elites(values, 0.5), [4.0, 2.0, 1.0])
    # two elites 2 apart: weights 1 and e^(-2 T), normalised; a softer (smaller) temperature spreads the weight
    for temperature in (0.5, 1 / 6):
        w = np.array([1.0, np.exp(-2.0 * temperature)])
        w /= w.sum()
        assert plan_std.effective_elites(np.array([1.0, -1.0]), temperature) == pytest.approx(1 / np.sum(w ** 2))
    softer, trained = (plan_std.effective_elites(np.array([1.0, -1.0]), t) for t in (1 / 6, 0.5))
    assert softer > trained


def test_command_plays_cli_evals_episodes_for_each_trained_seed(tmp_path, monkeypatch, capsys):
    """``main`` over a run of 2 trained seeds (its policy and environment given by the two loaders it calls, here
    the toy environment: no MuJoCo to compile): each seed's episodes are those `cli eval` plays (the returns of
    ``mjx_evaluator``, its program, with the same key), every agent step is a CSV row, the table holds each seed's
    mean return and share under the floors, a progress line follows each seed's episodes, and bad options exit with
    status 2."""
    import types

    from lnnmpc.train import evaluate, setup

    env = LinearEnv()
    agent = make_agent("cfc-zp-det", OBS_DIM, ACT_DIM, small=True)
    states = [perturbed_state(agent, jax.random.key(k)) for k in (5, 6)]
    seeds = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *states)  # the trained seeds' axis
    policy = evaluate.Policy(config=types.SimpleNamespace(seeds=2, eval_obs={}),
                             loop=types.SimpleNamespace(agent=agent, env=env), agent_state=seeds, checkpoint=8)
    monkeypatch.setattr(evaluate, "load_policy", lambda run, checkpoint=None: policy)
    monkeypatch.setattr(setup, "config_env", lambda config, options: env)
    out = tmp_path / "std.csv"
    assert plan_std.main(["my-run", "--episodes", "3", "--seed", "7", "--floors", "0.1", "--temperatures", "0.1",
                          "--out", str(out)]) == 0
    captured = capsys.readouterr()
    table = captured.out
    for seed in (0, 1):  # a progress line per trained seed, ended
        assert f"4/4 agent steps of 3 episodes, my-run seed {seed}" in captured.err
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 2 * 3 * 4 and {r["run"] for r in rows} == {"my-run"}
    expected = evaluate.mjx_evaluator(agent, env, episodes=3, seeds=2)(seeds, jax.random.key(7))  # (2, 3)
    for seed in (0, 1):
        mine = [r for r in rows if r["seed"] == str(seed)]
        totals = [sum(float(r["reward"]) for r in mine if r["episode"] == str(e)) for e in range(3)]
        np.testing.assert_allclose(totals, expected[seed], rtol=1e-5)
        line = next(x for x in table.splitlines() if x.startswith(f"| my-run | {seed} | 3 | "))
        assert float(line.split(" | ")[3]) == pytest.approx(np.mean(totals), abs=0.051)
        share = np.mean([float(r["std"]) < 0.1 for r in mine])
        cells = line.rstrip(" |").split(" | ")
        assert cells[-4] == f"{share:.2f}" and cells[-3] == f"{agent.config.planner.temperature:g}"
        for cell, column in zip(cells[-2:], ("ess_planner", "ess_0.1"), strict=True):
            ess = [float(r[column]) for r in mine]
            assert 1 <= min(ess) and max(ess) <= agent.config.planner.num_elites
            assert cell == f"{np.median(ess):.1f}"
        assert np.median([float(r["ess_0.1"]) for r in mine]) >= np.median([float(r["ess_planner"]) for r in mine])
    assert plan_std.main(["my-run", "--floors", "0.2,x"]) == 2
    assert "--floors takes positive numbers separated by commas, got '0.2,x'" in capsys.readouterr().err
    assert plan_std.main(["my-run", "--episodes", "0"]) == 2
    assert "episodes must be an integer >= 1, got 0" in capsys.readouterr().err
