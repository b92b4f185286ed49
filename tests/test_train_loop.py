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


@pytest.fixture(scope="module")
def init(loop):
    """``loop.init`` over 2 seeds, compiled once for the module (compiling it costs more than running it)."""
    return jax.jit(jax.vmap(loop.init))


def test_seed_phase_fills_replay_with_whole_episodes(loop, init):
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


def test_checkpoint_round_trip_of_a_train_state(init, tmp_path):
    from lnnmpc.train.checkpoint import latest_step, restore_checkpoint, save_checkpoint

    ts = init(jax.random.split(jax.random.key(9), 2))
    save_checkpoint(str(tmp_path), 7, ts, {"env_steps": 7})
    assert latest_step(str(tmp_path)) == 7
    like = init(jax.random.split(jax.random.key(10), 2))
    restored, host = restore_checkpoint(str(tmp_path), 7, like)
    assert host == {"env_steps": 7}
    for a, b in zip(jax.tree_util.tree_leaves(ts), jax.tree_util.tree_leaves(restored), strict=True):
        if jax.numpy.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
