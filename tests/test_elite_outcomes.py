"""``lnnmpc.analysis.elite_outcomes``: MPPI's elites played from a state on the environment, against their values."""

from __future__ import annotations

import csv

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lnn_helpers import LinearEnv, perturbed_state, quick_jit

from lnnmpc.agents.registry import make_agent
from lnnmpc.analysis import elite_outcomes as eo
from lnnmpc.train.config import ConfigError

OBS_DIM, ACT_DIM = LinearEnv.observation_size, LinearEnv.action_size


def test_elite_rollouts_play_the_elites_actions_then_the_agents_own():
    """Each elite's H planned actions step the environment as a hand-written loop of x' = 0.9 x + a does, the
    encoder reading each step as ``observe`` would, and then the agent acts on as its own ``act`` does."""
    env = LinearEnv()
    agent = make_agent("cfc-zp-det", OBS_DIM, ACT_DIM, small=True)
    state = perturbed_state(agent, jax.random.key(0))
    s0 = env.reset(jax.random.key(1))
    carry0, key, follow = agent.initial_carry(), jax.random.key(2), 1
    ranks = jnp.array([0, agent.config.planner.num_elites - 1])
    predicted, rewards = quick_jit(lambda: eo.elite_rollouts(agent, state, env, s0, carry0, key, ranks, follow))()
    _, _, info = quick_jit(lambda: agent.act_planned(state, carry0, s0.obs, s0.dt, key, explore=False,
                                                     first_step=jnp.asarray(True)))()
    np.testing.assert_allclose(predicted, np.asarray(info["elite_values"])[[0, -1]], rtol=1e-6)
    horizon = agent.config.planner.horizon
    assert rewards.shape == (2, horizon + follow)
    act = quick_jit(lambda c, o, k: agent.act(state, c, o, jnp.asarray(1.0), k, explore=False,
                                              first_step=jnp.asarray(False)))
    observe = quick_jit(lambda c, o, a, f: agent.observe(state, c, o, jnp.asarray(1.0), a, first_step=f))
    for i, rank in enumerate((0, agent.config.planner.num_elites - 1)):
        x, carry, paid = np.asarray(s0.obs, np.float64), carry0, []
        for t in range(horizon):  # the elite's actions, by hand
            a = np.asarray(info["elite_actions"])[t, rank]
            carry = observe(carry, jnp.asarray(x, jnp.float32), jnp.asarray(a), jnp.asarray(t == 0))
            x = 0.9 * x + np.pad(a, (0, OBS_DIM - ACT_DIM))
            paid.append(-np.sum(x ** 2))
        for j in range(follow):  # then the agent's own deterministic acting
            a, carry = act(carry, jnp.asarray(x, jnp.float32), jax.random.fold_in(key, j + 1))
            x = 0.9 * x + np.pad(np.asarray(a, np.float64), (0, OBS_DIM - ACT_DIM))
            paid.append(-np.sum(x ** 2))
        np.testing.assert_allclose(rewards[i], paid, rtol=1e-4, atol=1e-5)
    assert not np.allclose(rewards[0], rewards[1])  # two elites, two paths


def test_helpers_against_their_definitions():
    assert eo.hanging_step(np.array([0.5, 0.05, 0.0, 0.3]), 0.1, last=3) == 1
    assert eo.hanging_step(np.array([0.5, 0.2, 0.05]), 0.1, last=1) is None
    rewards = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 4.0]])
    np.testing.assert_allclose(eo.discounted(rewards, 0.9), [1 + 0.9 * 2 + 0.81 * 3, 0.81 * 4])
    assert eo.rank_correlation(np.array([1.0, 2.0, 3.0]), np.array([10.0, 30.0, 50.0])) == pytest.approx(1.0)
    assert eo.rank_correlation(np.array([1.0, 2.0, 3.0, 4.0]), np.array([4.0, 3.0, 2.0, 1.0])) == pytest.approx(-1.0)
    assert eo.rank_correlation(np.array([1.0, 3.0, 2.0]), np.array([1.0, 2.0, 3.0])) == pytest.approx(0.5)
    assert np.isnan(eo.rank_correlation(np.array([1.0, 1.0]), np.array([1.0, 2.0])))
    assert np.isnan(eo.rank_correlation(np.array([1.0, 2.0]), np.array([0.0, 1e-9])))  # round-off is no ranking
    np.testing.assert_allclose(eo.average_ranks(np.array([3.0, 1.0, 3.0, 2.0])), [2.5, 0.0, 2.5, 1.0])
    # ties: the mean-rank Pearson of (1, 2, 2, 3) and (1, 2, 3, 4), by hand
    rx, ry = np.array([0, 1.5, 1.5, 3]), np.arange(4.0)
    expected = np.sum((rx - rx.mean()) * (ry - ry.mean())) / np.sqrt(np.sum((rx - rx.mean()) ** 2)
                                                                     * np.sum((ry - ry.mean()) ** 2))
    assert eo.rank_correlation(np.array([1.0, 2.0, 2.0, 3.0]), np.arange(4.0)) == pytest.approx(expected)
    np.testing.assert_array_equal(eo.elite_ranks(64, 4), [0, 21, 42, 63])
    for bad in (1, 65):
        with pytest.raises(ConfigError, match=rf"--elites must be an integer in \[2, 64\].*got {bad}"):
            eo.elite_ranks(64, bad)


def test_command_follows_each_episodes_first_hanging_step(tmp_path, monkeypatch, capsys):
    """``main`` on a run of the toy environment (its policy and environment given by the loaders it calls): one
    CSV row per episode and elite, from the episode's first step (every step of the toy pays under 0.1), each
    elite's values those MPPI gave at that step, the table one row per episode; bad options exit with status 2."""
    import types

    from lnnmpc.train import evaluate, setup

    env = LinearEnv()
    agent = make_agent("cfc-zp-det", OBS_DIM, ACT_DIM, small=True)
    seeds = jax.tree_util.tree_map(lambda x: x[None], perturbed_state(agent, jax.random.key(5)))
    policy = evaluate.Policy(config=types.SimpleNamespace(seeds=1, eval_obs={}),
                             loop=types.SimpleNamespace(agent=agent, env=env), agent_state=seeds, checkpoint=8)
    monkeypatch.setattr(evaluate, "load_policy", lambda run, checkpoint=None: policy)
    monkeypatch.setattr(setup, "config_env", lambda config, options: env)
    out = tmp_path / "elites.csv"
    assert eo.main(["my-run", "--episodes", "2", "--elites", "3", "--follow", "1", "--out", str(out)]) == 0
    table = capsys.readouterr().out
    rows = list(csv.DictReader(open(out)))
    assert [(r["episode"], r["t"], r["rank"]) for r in rows] == [(e, "0", k) for e in "01" for k in ("0", "4", "7")]
    for episode in (0, 1):
        mine = [r for r in rows if r["episode"] == str(episode)]
        predicted = [float(r["predicted"]) for r in mine]
        assert predicted == sorted(predicted, reverse=True)  # ranks 0, 4, 7: best first
        assert all(float(r["paid_sum"]) < 0 for r in mine)
        assert any(line.startswith(f"| {episode} | 0 | 3 | ") for line in table.splitlines())
    assert eo.main(["my-run", "--elites", "1"]) == 2
    assert "--elites must be an integer in [2, 8]" in capsys.readouterr().err
    assert eo.main(["my-run", "--elites", "3", "--follow", "5"]) == 2
    assert "--follow 5 plus the plan's 3 steps exceed the episode's 4 agent steps" in capsys.readouterr().err
