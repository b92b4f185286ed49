"""The training loop learns: a CPU-sized TD-MPC2 on cartpole-swingup beats its untrained self.

Deterministic MPPI returns of the freshly initialised agent (zero-initialised reward and Q heads: it cannot tell
actions apart) are compared with those after a seed phase, an update burst and closed-loop training with one
update per agent step — the schedule of SPEC §1 at toy scale. Both seeds must improve by a wide margin.
Measured on CPU (seed 0, jax 0.10.2): before 0.0 / 21.1, after 204.1 / 141.6 (with the model of runs before
2026-11-23, no LayerNorm before SimNorm, weights cut at ±2σ, one pair of Q heads per act call: 10.1 / 24.2 and
207.6 / 160.4; float32 round-off alone, e.g. XLA's optimisation level 0, moved those to 176.1 / 175.0).
"""

import jax
import numpy as np

from lnnmpc import envs
from lnnmpc.agents.registry import make_agent
from lnnmpc.train.loop import LoopConfig, TrainingLoop

SEEDS, SEED_ITERATIONS, TRAIN_ITERATIONS = 2, 501, 600


def test_tdmpc2_improves_its_return_on_cartpole_swingup():
    env = envs.make("cartpole-swingup")
    agent = make_agent("tdmpc2", env.observation_size, env.action_size, small=True)
    loop = TrainingLoop(agent, env, env, LoopConfig(batch_size=64, replay_capacity=3000, eval_episodes=4))
    ts = jax.jit(jax.vmap(loop.init))(jax.random.split(jax.random.key(0), SEEDS))
    evaluate = jax.jit(jax.vmap(loop.evaluate))
    eval_keys = jax.random.split(jax.random.key(1), SEEDS)
    before = np.asarray(evaluate(ts.agent, eval_keys)).mean(axis=1)

    chunk = lambda fn: jax.jit(jax.vmap(fn, in_axes=(0, None)), static_argnums=1)
    ts, _ = chunk(loop.seed_chunk)(ts, SEED_ITERATIONS)
    ts, _ = chunk(loop.update_burst)(ts, SEED_ITERATIONS - 1)
    ts, out = chunk(loop.train_chunk)(ts, TRAIN_ITERATIONS)
    assert np.isfinite(np.asarray(out["total_loss"])).all()
    after = np.asarray(evaluate(ts.agent, eval_keys)).mean(axis=1)

    assert (before < 60).all(), before  # hanging pole, no swing: almost no reward
    assert (after > before + 60).all() and after.mean() > 100, (before, after)
