"""Parity of the MJX environments with dm_control (CPU, float64, physics="exact", action_repeat=1)."""

from __future__ import annotations

import dm_reference
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc import envs
from lnnmpc.envs.tasks import TASKS

# (task stepped, other tasks of the same domain whose rewards are read off the same physics, steps)
DOMAINS = [
    ("cartpole-swingup", ("cartpole-swingup-sparse", "cartpole-balance", "cartpole-balance-sparse"), 100),
    ("acrobot-swingup", ("acrobot-swingup-sparse",), 100),
    ("walker-run", ("walker-stand", "walker-walk"), 20),
]


def _mjx_rollout_fn(task, extra):
    """A jitted (qpos, qvel, actions) -> (obs (T + 1, obs_dim), rewards (T, n_tasks)); build under x64."""
    env = envs.make(task, physics="exact", action_repeat=1)
    names = (task, *extra)

    def run(qpos, qvel, actions):
        state = env.reset_to(qpos, qvel)

        def body(state, action):
            state = env.step(state, action)
            rewards = jnp.stack([TASKS[n].reward(state.physics, action, env.ids) for n in names])
            return state, (state.obs, rewards)

        _, (obs, rewards) = jax.lax.scan(body, state, actions)
        return state.obs, obs, rewards

    jitted = jax.jit(run)

    def rollout(qpos, qvel, actions):
        first, obs, rewards = jitted(qpos, qvel, actions)
        return np.concatenate([first[None], obs]), dict(zip(names, np.asarray(rewards).T, strict=True))

    return rollout


@pytest.fixture(autouse=True)
def fresh_jit_caches(monkeypatch):
    """JAX's caches of inner jitted functions (MJX's ``jit(tril)`` in RK4) do not tell x64 from x32 programs:
    one traced by an earlier float32 test in the same worker breaks the float64 lowering here (operand type
    mismatch), and the reverse would leak float64 into later tests. Clear them on the way in and out.

    That is not enough once test_trainer_run's evaluation with the policy prior has run in the worker (that test,
    then this file, in one process: cartpole fails without the copies below, passes with them): RK4's Butcher
    tableau, numpy arrays that MJX keeps at module level, still came into the float64 trace as float32 arguments of
    ``jit(tril)``, so JAX keeps something of those very objects past ``clear_caches``. Fresh copies of them here,
    equal in value, are objects it has not met."""
    from mujoco.mjx._src import forward

    monkeypatch.setattr(forward, "_RK4_A", np.array(forward._RK4_A, copy=True))
    monkeypatch.setattr(forward, "_RK4_B", np.array(forward._RK4_B, copy=True))
    jax.clear_caches()
    yield
    jax.clear_caches()


@pytest.mark.parametrize("task,extra,steps", DOMAINS, ids=[d[0].split("-")[0] for d in DOMAINS])
def test_exact_physics_matches_dm_control(task, extra, steps):
    rng = np.random.default_rng(7)
    nu = dm_reference.load(task, 0).action_spec().shape[0]
    with jax.enable_x64(True):
        mjx_rollout = _mjx_rollout_fn(task, extra)
    for seed in (0, 1):
        actions = rng.uniform(-1, 1, size=(steps, nu))
        qpos, qvel, ref_obs, ref_rewards = dm_reference.rollout(task, seed, actions, extra)
        with jax.enable_x64(True):
            obs, rewards = mjx_rollout(qpos, qvel, actions)
        assert obs.dtype == np.float64
        print(f"{task} seed {seed}: max obs err {np.abs(obs - ref_obs).max():.2e}, "
              f"max reward err {np.abs(rewards[task] - ref_rewards[task]).max():.2e}")
        np.testing.assert_allclose(obs, ref_obs, rtol=0, atol=1e-8)
        for name in (task, *extra):
            np.testing.assert_allclose(rewards[name], ref_rewards[name], rtol=0, atol=1e-8, err_msg=name)
        # The rollout must exercise the reward functions, not sit at a constant.
        assert np.ptp(ref_rewards[task]) > 1e-3 or task.startswith("walker")
