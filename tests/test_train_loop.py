"""The on-device training loop: schedule pieces, replay contents, and learning on a tiny cartpole run."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from lnnmpc import envs
from lnnmpc.agents.mppi import MPPIConfig
from lnnmpc.agents.tdmpc2 import TDMPC2, TDMPC2Config
from lnnmpc.agents.tdmpc2_model import WorldModelConfig
from lnnmpc.replay import replay_size
from lnnmpc.train.loop import LoopConfig, TrainingLoop


@pytest.fixture(scope="module")
def loop():
    env = envs.make("cartpole-balance")
    model = WorldModelConfig.from_size(env.observation_size, env.action_size, 1, enc_dim=32, mlp_dim=32,
                                       latent_dim=16, num_q=2)
    planner = MPPIConfig(num_samples=32, num_policy_trajectories=4, num_elites=4, iterations=1)
    agent = TDMPC2(TDMPC2Config(model=model, planner=planner))
    return TrainingLoop(agent, env, env, LoopConfig(num_envs=2, batch_size=32, replay_capacity=2000,
                                                    eval_episodes=2))


def test_seed_phase_fills_replay_with_whole_episodes(loop):
    init = jax.jit(jax.vmap(loop.init))
    seed = jax.jit(jax.vmap(loop.seed_chunk, in_axes=(0, None)), static_argnums=1)
    ts, out = seed(init(jax.random.split(jax.random.key(0), 2)), 502)  # one episode (500 steps + final obs) + 1
    assert np.asarray(replay_size(ts.replay)).tolist() == [502, 502]
    returns = np.asarray(out["episode_return"])  # (seeds, iterations, envs), NaN except where an episode ended
    ended = ~np.isnan(returns)
    assert ended.sum() == 4 and ended[:, 500].all()  # both envs of both seeds end at iteration 500
    rewards = np.asarray(out["reward"])
    np.testing.assert_allclose(returns[:, 500], rewards[:, :500].sum(axis=1), rtol=1e-5)
    first = np.asarray(ts.replay.first)  # (seeds, capacity, envs)
    assert first[:, 0].all() and first[:, 501].all() and not first[:, 1:501].any()
    # The terminal record carries the final observation with a zero action and reward.
    assert np.all(np.asarray(ts.replay.fields["action"])[:, 500] == 0)
    assert np.all(np.asarray(ts.replay.fields["reward"])[:, 500] == 0)


def test_updates_and_training_chunk_run_and_learn(loop):
    init = jax.jit(jax.vmap(loop.init))
    seed = jax.jit(jax.vmap(loop.seed_chunk, in_axes=(0, None)), static_argnums=1)
    burst = jax.jit(jax.vmap(loop.update_burst, in_axes=(0, None)), static_argnums=1)
    train = jax.jit(jax.vmap(loop.train_chunk, in_axes=(0, None)), static_argnums=1)
    ts, _ = seed(init(jax.random.split(jax.random.key(1), 2)), 300)
    ts, metrics = burst(ts, 60)
    reward_loss = np.asarray(metrics["reward_loss"])  # (seeds, updates)
    assert np.all(reward_loss[:, -10:].mean(1) < reward_loss[:, :5].mean(1) - 0.2)
    ts, out = train(ts, 20)
    assert np.asarray(ts.agent.updates).tolist() == [60 + 40, 60 + 40]  # num_envs updates per iteration
    assert all(np.all(np.isfinite(np.asarray(v))) for k, v in out.items() if k != "episode_return")
    returns = jax.jit(jax.vmap(loop.evaluate))(ts.agent, jax.random.split(jax.random.key(2), 2))
    assert returns.shape == (2, 2) and np.all(np.isfinite(np.asarray(returns)))
