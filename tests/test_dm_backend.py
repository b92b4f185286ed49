"""lnnmpc.train.dm_backend.run_episodes: an episode on dm_control is the same whichever episodes and seeds play
beside it, so `make video` films exactly the episode `make eval --backend dm_control` scored."""

import dataclasses

import jax
import numpy as np
import pytest

from lnnmpc import envs
from lnnmpc.agents.registry import make_agent
from lnnmpc.train.dm_backend import episode_keys, run_episodes


def test_an_episode_plays_alike_alone_and_among_many():
    """Seed 1's first two episodes of a 2-seed x 3-episode evaluation, replayed with that seed's policy alone (as
    `video` slices it, ``seed_ids=[1]``) and two episodes: the same returns to the last bit. Another key gives
    other returns (the untrained planner's choices are its random draws), so equality is not a constant."""
    env = envs.make("cartpole-swingup")
    env = dataclasses.replace(env, spec=dataclasses.replace(env.spec, control_steps=40 * env.action_repeat))
    agent = make_agent("cfc-zp-det", env.observation_size, env.action_size, small=True)
    states = jax.jit(jax.vmap(agent.init))(jax.random.split(jax.random.key(5), 2))
    seed_1 = jax.tree_util.tree_map(lambda x: x[1:2], states)
    together = run_episodes(env, agent, states, 3, jax.random.key(7), seed=4)
    alone = run_episodes(env, agent, seed_1, 2, jax.random.key(7), seed=4, seed_ids=[1])
    np.testing.assert_array_equal(alone[0], together[1, :2])
    assert np.all(together > 0) and len(np.unique(together)) == together.size
    other_key = run_episodes(env, agent, seed_1, 2, jax.random.key(8), seed=4, seed_ids=[1])
    assert not np.allclose(other_key, alone)
    with pytest.raises(ValueError, match="seed_ids has 2 entries for 1 seed"):
        run_episodes(env, agent, seed_1, 1, jax.random.key(7), seed_ids=[0, 1])


def test_episode_keys_fold_the_seed_and_the_episode_in():
    key = jax.random.key(3)
    keys = jax.random.key_data(episode_keys(key, [2, 5], 3))
    assert keys.shape[0] == 6
    expected = jax.random.key_data(jax.random.fold_in(jax.random.fold_in(key, 5), 1))
    np.testing.assert_array_equal(keys[4], expected)  # seed-major: row 4 is seed 5's episode 1
    assert len({tuple(np.asarray(k).ravel()) for k in keys}) == 6
