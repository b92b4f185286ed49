"""The on-device training loop: schedule pieces, replay contents, and learning on a tiny cartpole run."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from lnnmpc import envs
from lnnmpc.agents.mppi import MPPIConfig
from lnnmpc.agents.tdmpc2 import TDMPC2, TDMPC2Config
from lnnmpc.agents.tdmpc2_model import WorldModelConfig
from lnnmpc.replay import replay_add, replay_init, replay_num_windows, replay_size
from lnnmpc.train.loop import LoopConfig, TrainingLoop, windows_after_seed_phase


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


@pytest.fixture(scope="module")
def seeded(loop, init):
    """2 seeds after 502 seed-phase iterations: one episode (500 steps + final obs) and the next one's first."""
    seed = jax.jit(jax.vmap(loop.seed_chunk, in_axes=(0, None)), static_argnums=1)
    return seed(init(jax.random.split(jax.random.key(0), 2)), 502)


def test_seed_phase_fills_replay_with_whole_episodes(seeded):
    ts, out = seeded
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


def _windows_per_iteration(episode_records: int, length: int, lead: int, capacity: int, iterations: int):
    """(iterations,) valid windows of one stream after each iteration of the loop's schedule (one record per
    iteration, an episode of ``episode_records`` records), counted by the replay buffer itself."""
    state = replay_init({"x": jnp.zeros(())}, capacity, 1)

    def body(state, i):
        state = replay_add(state, {"x": jnp.ones((1,))}, (i % episode_records == 0)[None])
        return state, replay_num_windows(state, length, lead)

    return np.asarray(jax.lax.scan(body, state, jnp.arange(iterations))[1])


def test_windows_after_seed_phase_is_what_the_buffer_holds_ever_after():
    """Where :func:`windows_after_seed_phase` says yes, the buffer holds a valid window from that iteration on,
    through the ring's overwrites; one iteration short of the window it holds none; and its capacity clause is
    needed (a smaller ring loses every window at some episode boundary)."""
    lost_without_capacity_clause = 0
    for episode_length in (3, 6):
        for length in (2, 4, 5, 7):
            for capacity in range(length, 2 * length + 1):
                iterations = 4 * (episode_length + 1) + 2 * capacity
                for lead in sorted({0, length - 1}):
                    counts = _windows_per_iteration(episode_length + 1, length, lead, capacity, iterations)
                    assert counts[length - 2] == 0  # after length - 1 records no window can exist
                    for n in range(1, iterations + 1):
                        if windows_after_seed_phase(n, episode_length, length, capacity):
                            assert (counts[n - 1:] > 0).all(), (episode_length, length, capacity, lead, n)
                    if (lead == 0 and episode_length + 1 >= length and capacity < 2 * length - 1
                            and (counts[length - 1:] == 0).any()):
                        lost_without_capacity_clause += 1
    assert lost_without_capacity_clause > 0


def test_the_trainer_drops_the_empty_replay_guard_only_after_a_long_enough_seed_phase():
    from lnnmpc.train.config import TrainConfig
    from lnnmpc.train.setup import build_loop

    base = dict(task="cartpole-swingup", small=True, model_size=1, envs=2)
    assert not build_loop(TrainConfig(**base)).config.guard_empty_replay  # 5000 steps: 313 iterations
    # 8 steps: one iteration of 2 environments, fewer records than the agent's window of H + 1
    assert build_loop(TrainConfig(**base, seed_steps=8)).config.guard_empty_replay
    assert build_loop(TrainConfig(**base, seed_steps=0)).config.guard_empty_replay


def test_update_without_the_guard_leaves_it_out_and_equals_the_guarded_update(loop, seeded):
    """Dropping the select changes no number of an update on a buffer with windows (2 updates in one scan, 2
    seeds), and the compiled update no longer carries the ``keep_if_valid`` scope."""
    import dataclasses

    unguarded = TrainingLoop(loop.agent, loop.env, loop.eval_env,
                             dataclasses.replace(loop.config, guard_empty_replay=False))
    ts = seeded[0]
    keys = jax.random.split(jax.random.key(3), 2)
    for each, present in ((loop, True), (unguarded, False)):
        hlo = jax.jit(jax.vmap(each._update)).lower(ts, keys).as_text(debug_info=True)
        assert ("keep_if_valid" in hlo) is present
    burst = lambda each: jax.jit(jax.vmap(each.update_burst, in_axes=(0, None)), static_argnums=1)(ts, 2)[0]
    with_guard, without = burst(loop), burst(unguarded)
    for a, b in zip(jax.tree_util.tree_leaves(with_guard.agent), jax.tree_util.tree_leaves(without.agent),
                    strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)
    moved = [not np.array_equal(np.asarray(a), np.asarray(b)) for a, b in
             zip(jax.tree_util.tree_leaves(ts.agent), jax.tree_util.tree_leaves(without.agent), strict=True)
             if jnp.issubdtype(a.dtype, jnp.floating)]
    assert any(moved)  # the updates did change the agent (the buffer had windows)


def test_guarded_update_on_an_empty_buffer_keeps_the_agent(loop, init):
    ts = init(jax.random.split(jax.random.key(5), 2))  # nothing written yet
    keys = jax.random.split(jax.random.key(6), 2)
    after = jax.jit(jax.vmap(loop._update))(ts, keys)[0]
    for a, b in zip(jax.tree_util.tree_leaves(ts.agent), jax.tree_util.tree_leaves(after.agent), strict=True):
        if jax.numpy.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_more_evaluation_episodes_with_the_same_key_extend_the_set(loop, seeded):
    """Episode i of an evaluation depends on the key and i alone: 3 episodes are 2 episodes' returns plus one,
    and another key gives other episodes. The episodes are _ToyEnv's (below: initial states drawn from the reset
    key, no physics), so the two evaluation programs compile in seconds; the MJX environment's own use of its key
    is test_env_api's and test_env_init's."""
    import dataclasses

    from lnn_helpers import quick_jit

    agent = jax.tree_util.tree_map(lambda x: x[0], seeded[0].agent)  # seed 0's agent (untrained: any policy will do)
    evaluate = {n: quick_jit(TrainingLoop(loop.agent, loop.env, _ToyEnv(),
                                          dataclasses.replace(loop.config, eval_episodes=n)).evaluate) for n in (2, 3)}
    key = jax.random.key(11)
    two, three = (np.asarray(evaluate[n](agent, key)) for n in (2, 3))
    np.testing.assert_allclose(three[:2], two, rtol=1e-5)
    assert len(set(np.round(three, 4))) == 3  # three different episodes
    assert not np.allclose(np.asarray(evaluate[2](agent, jax.random.key(12))), two)


@struct.dataclass
class _ToyState:
    obs: jax.Array
    dt: jax.Array
    t: jax.Array
    reward: jax.Array


class _ToyEnv:
    """Evaluation episodes of 20 steps without physics (their programs compile in seconds): the observation (5,)
    starts N(0, 1) from the reset key and moves by the action, the reward is exp(-|o|^2)."""

    episode_length = 20

    def reset(self, key: jax.Array) -> _ToyState:
        return _ToyState(obs=jax.random.normal(key, (5,)), dt=jnp.ones(()), t=jnp.zeros((), jnp.int32),
                         reward=jnp.zeros(()))

    def step(self, state: _ToyState, action: jax.Array) -> _ToyState:
        obs = 0.9 * state.obs + 0.5 * action[0]
        return _ToyState(obs=obs, dt=state.dt, t=state.t + 1, reward=jnp.exp(-jnp.sum(obs**2)))


def test_evaluation_with_the_prior_plays_the_same_episodes_with_the_prior_acting(loop, seeded):
    """``eval_prior``: one program returns MPPI's returns and ranks as without it, and the returns of the same
    episodes (keys, initial states) with the policy prior acting: those of a loop whose agent acts with the prior
    (``with_actor``), evaluated with the same key."""
    import dataclasses

    from lnn_helpers import quick_jit

    from lnnmpc.agents.actor import with_actor

    config = dataclasses.replace(loop.config, eval_episodes=3)
    evaluate = lambda acting, **changes: quick_jit(TrainingLoop(acting, loop.env, _ToyEnv(), dataclasses.replace(
        config, **changes)).evaluate_logged)
    agent, key = jax.tree_util.tree_map(lambda x: x[0], seeded[0].agent), jax.random.key(11)
    planner, both, alone = ({k: np.asarray(v) for k, v in evaluate(acting, **changes)(agent, key).items()}
                            for acting, changes in ((loop.agent, {}), (loop.agent, {"eval_prior": True}),
                                                    (with_actor(loop.agent, "prior"), {})))
    assert set(planner) == {"return", "effective_rank"} and set(both) == {"return", "effective_rank", "prior_return"}
    np.testing.assert_allclose(both["return"], planner["return"], rtol=1e-6)
    np.testing.assert_allclose(both["effective_rank"], planner["effective_rank"], rtol=1e-6)
    np.testing.assert_allclose(both["prior_return"], alone["return"], rtol=1e-6)
    # another actor, not MPPI again (untrained, the two act alike: returns 0.02-0.04 apart; round-off ~1e-5)
    assert np.abs(both["prior_return"] - both["return"]).max() > 1e-3
    assert len(set(np.round(both["prior_return"], 4))) == 3  # three episodes, from three initial states
    with pytest.raises(ValueError, match="eval_prior must be True or False, got 1"):
        LoopConfig(eval_prior=1)
