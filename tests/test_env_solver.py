"""The unrolled constraint solver gives MJX's own iterates (it only removes the while_loop)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc import envs


def _final_states(task: str, options: envs.PhysicsOptions, steps: int) -> np.ndarray:
    env = envs.make(task, physics=options)

    def episode(key):
        k_reset, k_act = jax.random.split(key)
        state = env.reset(k_reset)
        side = jnp.where(jax.random.bernoulli(k_reset), 1.0, -1.0)
        actions = jnp.clip(0.5 * side + 0.5 * jax.random.uniform(k_act, (steps, env.action_size), minval=-1), -1, 1)

        def body(state, action):
            state = env.step(state, action)
            return state, jnp.concatenate([state.physics.qpos, state.physics.qvel])

        return jax.lax.scan(body, state, actions)[1]

    return np.asarray(jax.jit(jax.vmap(episode))(jax.random.split(jax.random.key(5), 4)))


# walker compiles with XLA's optimisations (conftest): under jax_disable_most_optimizations the two solvers' walker
# states differ by round-off that 8 steps of contacts grow to 4e-3; cartpole's stay within 1e-5 either way
@pytest.mark.parametrize("task,iterations,steps", [
    ("cartpole-swingup", 2, 120), pytest.param("walker-run", 3, 8, marks=pytest.mark.full_optimisation)])
def test_unrolled_solver_equals_mjx_while_loop(task, iterations, steps):
    options = envs.PhysicsOptions(iterations=iterations, ls_iterations=3)
    looped = _final_states(task, options, steps)
    unrolled = _final_states(task, dataclasses.replace(options, unrolled_solver=True), steps)
    assert np.all(np.isfinite(unrolled))
    np.testing.assert_allclose(unrolled, looped, rtol=0, atol=1e-5)


def test_unrolled_solver_patch_is_scoped():
    from mujoco.mjx._src import solver as mjx_solver

    from lnnmpc.envs.solver import unrolled_solve, unrolled_solver

    original = mjx_solver.solve
    with unrolled_solver():
        assert mjx_solver.solve is unrolled_solve
    assert mjx_solver.solve is original
