"""The "fast" physics profile against "exact" (float32, action repeat 2).

Tolerances and why:
* cartpole / acrobot: "fast" only lowers solver effort. Acrobot has constraints disabled; cartpole's only
  constraint is the slider limit, which two Newton iterations resolve exactly (one iteration does not: the pole's
  angular velocity is off by ~0.5 after the cart hits the end of the rail). Rollouts are pushed into the limit,
  and both profiles must agree to float32 round-off (1e-4 over 150 agent steps).
* walker: contacts make the dynamics chaotic (a 1e-6 change of the initial state grows to O(1) in ~50 agent
  steps even under "exact"), so trajectories are compared only up to the first ground contacts (2 agent steps,
  positions and orientations within 1e-2) and then statistically: mean returns of random-action episodes must
  agree within 3 standard errors, and no velocity may exceed twice exact's largest. A solver that is too weak
  fails the latter: measured 2026-11-26 (24 episodes x 80 agent steps), iterations 2 / line search 4 reached a
  velocity of 140.6 against the bound 96.8 (fast: 56.0), while its mean return stayed within 0.1 standard
  errors of exact's (an earlier model of this test saw +25% return from it).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc import envs


def _rollouts(task: str, physics: str, n: int, steps: int, push: float = 0.0):
    """Random-action episodes from fixed keys: (clean obs (n, steps, d), rewards (n, steps)).

    ``push`` biases every action towards +1 or -1 (a random side per episode), e.g. to reach joint limits.
    """
    env = envs.make(task, physics=physics)

    def episode(key):
        k_reset, k_act = jax.random.split(key)
        state = env.reset(k_reset)
        actions = jax.random.uniform(k_act, (steps, env.action_size), minval=-1, maxval=1)
        side = jnp.where(jax.random.bernoulli(k_reset), 1.0, -1.0)
        actions = jnp.clip(push * side + (1 - push) * actions, -1, 1)

        def body(state, action):
            state = env.step(state, action)
            return state, (state.clean_obs, state.reward)

        return jax.lax.scan(body, state, actions)[1]

    obs, rewards = jax.jit(jax.vmap(episode))(jax.random.split(jax.random.key(42), n))
    return np.asarray(obs, np.float64), np.asarray(rewards, np.float64)


@pytest.mark.parametrize("task", ["cartpole-swingup", "acrobot-swingup"])
def test_fast_matches_exact_without_contacts(task):
    obs_exact, rew_exact = _rollouts(task, "exact", n=8, steps=150, push=0.6)
    obs_fast, rew_fast = _rollouts(task, "fast", n=8, steps=150, push=0.6)
    if task.startswith("cartpole"):
        assert np.abs(obs_exact[..., 0]).max() > 1.8  # the slider limit (1.8) was hit
    np.testing.assert_allclose(obs_fast, obs_exact, atol=1e-4)
    np.testing.assert_allclose(rew_fast, rew_exact, atol=1e-4)


def test_fast_walker_agrees_with_exact():
    n, steps = 24, 80  # the largest velocities come early; exact's while-loop solver costs ~0.17 s per agent step here
    obs_exact, rew_exact = _rollouts("walker-run", "exact", n, steps)
    obs_fast, rew_fast = _rollouts("walker-run", "fast", n, steps)
    assert np.all(np.isfinite(obs_fast))
    # Same state, same actions: positions/orientations (first 15 dims) agree until contacts take over.
    np.testing.assert_allclose(obs_fast[:, :2, :15], obs_exact[:, :2, :15], atol=1e-2)
    # Statistically equal returns; velocities stay physical.
    ret_exact, ret_fast = rew_exact.sum(1), rew_fast.sum(1)
    stderr = np.sqrt(ret_exact.var(ddof=1) / n + ret_fast.var(ddof=1) / n)
    assert abs(ret_fast.mean() - ret_exact.mean()) < 3 * stderr, (ret_fast.mean(), ret_exact.mean(), stderr)
    assert np.abs(obs_fast[..., 15:]).max() < 2 * np.abs(obs_exact[..., 15:]).max()


def test_fast_profile_is_cheaper_than_exact():
    """The profiles really differ where it matters (solver effort), and only there."""
    for domain, task in (("cartpole", "cartpole-swingup"), ("walker", "walker-run")):
        fast, exact = envs.make(task).mj_model.opt, envs.make(task, physics="exact").mj_model.opt
        assert fast.iterations < exact.iterations and fast.ls_iterations < exact.ls_iterations, domain
        assert fast.integrator == exact.integrator and fast.timestep == exact.timestep, domain
