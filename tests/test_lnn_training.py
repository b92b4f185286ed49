"""LNN-TD-MPC2 in training: the loop on cartpole-swingup (stored encoder states, closed-loop training) and every
variant's update and act step on a fixed batch and on cartpole-swingup windows.

The MJX environment's compilation dominates CPU time, so only one variant runs the full loop; the eight variants
share its replay buffer (same tiny sizes, so the same record shapes) for their updates and act steps.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lnn_helpers import quick_jit, tiny_agent

from lnnmpc import envs
from lnnmpc.agents.registry import LNN_AGENTS
from lnnmpc.replay import replay_sample
from lnnmpc.train.loop import LoopConfig, TrainingLoop

ITERATIONS, B, UPDATES = 14, 8, 6


@pytest.fixture(scope="module")
def run():
    """cfc-zp-det on cartpole-swingup, 2 environments, ITERATIONS of acting and training from scratch.

    The first windows of ``sequence_length`` = 8 records become valid after 8 iterations, so the acts of
    iterations 0..7 all use the initial parameters (updates before that are no-ops), and the rest train.
    """
    env = envs.make("cartpole-swingup")
    loop = TrainingLoop(tiny_agent("cfc-zp-det", env.observation_size, env.action_size), env, env,
                        LoopConfig(num_envs=2, batch_size=B, replay_capacity=600, eval_episodes=2))
    first = quick_jit(loop.init)(jax.random.key(0))
    ts, out = quick_jit(loop.train_chunk, static_argnums=1)(first, ITERATIONS)
    return loop, first, ts, out


def test_replay_stores_the_encoder_state_the_actor_had(run):
    loop, first, ts, _ = run
    agent, fields = loop.agent, jax.tree_util.tree_map(np.asarray, ts.replay.fields)
    n = loop.agent.sequence_length  # records written with the initial parameters
    assert np.asarray(ts.replay.first)[0].all() and not np.asarray(ts.replay.first)[1:ITERATIONS].any()
    assert np.all(fields["h_prev"][0] == 0) and np.all(fields["prev_action"][0] == 0)
    np.testing.assert_array_equal(fields["prev_action"][1:ITERATIONS], fields["action"][:ITERATIONS - 1])
    np.testing.assert_allclose(fields["dt"][:ITERATIONS], 1.0)
    # Re-encode the stored history from the episode start: h_t must be the state stored with record t + 1.
    states = agent.encode_sequence(first.agent.params, jnp.zeros((2, agent.config.model.hidden_size)),
                                   fields["obs"][:n], fields["prev_action"][:n], fields["dt"][:n])
    assert float(np.abs(fields["h_prev"][1:n]).max()) > 0.1
    np.testing.assert_allclose(fields["h_prev"][1:n], np.asarray(states[:n - 1]), rtol=1e-5, atol=1e-5)


def test_closed_loop_training_stays_finite(run):
    loop, first, ts, out = run
    assert int(ts.agent.updates) == (ITERATIONS - loop.agent.sequence_length + 1) * loop.config.num_envs
    for name in ("total_loss", "prediction_loss", "reward_loss", "value_loss", "policy_loss", "grad_norm"):
        assert np.isfinite(np.asarray(out[name])).all(), name
    leaves = jax.tree_util.tree_leaves(ts.agent.params)
    assert all(np.isfinite(np.asarray(x)).all() for x in leaves)
    moved = [float(jnp.abs(a - b).max()) for a, b in zip(leaves, jax.tree_util.tree_leaves(first.agent.params),
                                                         strict=True)]
    assert max(moved) > 0
    actions = np.asarray(ts.replay.fields["action"])[:ITERATIONS]
    assert np.all(np.abs(actions) <= 1) and np.abs(actions).max() > 0
    assert np.isfinite(np.asarray(ts.carry.h)).all() and float(np.abs(np.asarray(ts.carry.h)).max()) > 0


def test_the_loop_samples_windows_with_the_agents_lead(run, monkeypatch):
    """An agent with ``learn_episode_starts`` gets windows whose burn-in may reach back past their episode's start
    (``replay_sample``'s ``lead`` = its burn-in) and the records' ``first`` flags in its batch."""
    import lnnmpc.train.loop as loop_module

    loop, _, ts, _ = run
    calls = []
    real = loop_module.replay_sample
    monkeypatch.setattr(loop_module, "replay_sample", lambda *a: calls.append(a[3:]) or real(*a))
    agent = tiny_agent("cfc-zp-det", loop.env.observation_size, loop.env.action_size, learn_episode_starts=True)
    batches = []
    monkeypatch.setattr(agent, "update", lambda state, batch, key: batches.append(batch) or (state, {}))
    jax.eval_shape(TrainingLoop(agent, loop.env, loop.env, loop.config)._update, ts, jax.random.key(0))
    jax.eval_shape(loop._update, ts, jax.random.key(0))
    assert calls == [(agent.sequence_length, agent.config.burn_in), (agent.sequence_length, 0)]
    assert batches[0]["first"].shape == (agent.sequence_length, B) and batches[0]["first"].dtype == bool


# Every variant, and cfc-zp-det with its latent read off the state and the observation by a SimNorm head (12 wide,
# groups of 4, on the tiny encoder state of 8; without the skip in test_lnn_agents.py).
VARIANTS = [(name, {}) for name in LNN_AGENTS] + [
    ("cfc-zp-det", {"latent_head": "simnorm", "simnorm_dim": 4, "latent_size": 12, "latent_obs_skip": True})]


@pytest.mark.parametrize("name,overrides", VARIANTS, ids=[n + ("-simnorm-obs-skip" if o else "") for n, o in VARIANTS])
def test_each_variant_learns_a_fixed_batch_and_trains_on_cartpole(run, name, overrides):
    """One compiled program per variant: init, UPDATES updates on one fixed window batch, UPDATES on sampled
    cartpole-swingup windows, then two deterministic act steps."""
    loop, _, ts, _ = run
    agent = tiny_agent(name, loop.env.observation_size, loop.env.action_size, **overrides)
    assert agent.sequence_length == loop.agent.sequence_length
    keys = jax.random.split(jax.random.key(1), 2 * UPDATES)
    windows = jax.vmap(lambda k: replay_sample(ts.replay, k, B, agent.sequence_length)[0])(keys[:UPDATES])
    fixed = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x[0], x.shape), windows)
    batches = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), fixed, windows)

    @quick_jit
    def program(batches, obs, dt):
        state = agent.init(jax.random.key(2))
        state, metrics = jax.lax.scan(lambda s, bk: agent.update(s, *bk), state, (batches, keys))

        def act(carry, k):
            action, carry = agent.act(state, carry, obs, dt, k, explore=False, first_step=jnp.array(False))
            return carry, action

        carry, actions = jax.lax.scan(act, agent.initial_carry(), jax.random.split(jax.random.key(3), 2))
        return state, metrics, carry, actions

    state, metrics, carry, actions = jax.tree_util.tree_map(np.asarray, program(batches, ts.env.obs[0], ts.env.dt[0]))
    assert all(np.isfinite(v).all() for v in metrics.values())
    for loss in ("total_loss", "prediction_loss", "reward_loss", "value_loss"):
        on_fixed = metrics[loss][:UPDATES]
        assert on_fixed[-1] < on_fixed[0], (loss, on_fixed)
    assert all(np.isfinite(x).all() for x in jax.tree_util.tree_leaves(state.params))
    assert np.isfinite(actions).all() and np.all(np.abs(actions) <= 1)
    assert np.isfinite(carry.h).all() and np.isfinite(carry.plan_mean).all()
