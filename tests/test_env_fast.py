"""The "fast" physics profile (float32, action repeat 2) against dm_control: MuJoCo's C simulator in float64,
the exact reference (tests/test_env_parity.py holds the "exact" profile to it at 1e-8). Both play the same
initial states (dm_control's own initialisation) and the same actions; one MJX program per test.

Tolerances and why (measured 2026-12-05, AMD EPYC CPU):
* cartpole / acrobot: "fast" only lowers solver effort. Acrobot has constraints disabled; cartpole's only
  constraint is the slider limit, which two Newton iterations resolve exactly. Cartpole's rollouts are pushed into
  the limit (8 episodes x 150 agent steps): fast's largest difference from dm_control is 1.8e-4 in the
  observations and 3.8e-5 in the rewards, float32 against float64, against 1e-3 allowed; one Newton iteration
  is off by 0.73 and 0.17. Acrobot is chaotic, so float32 round-off alone grows to 2e-2 over 150 steps: over 50
  steps fast differs by 1.9e-5 (2e-4 allowed).
* walker: contacts make the dynamics chaotic (a 1e-6 change of the initial state grows to O(1) in ~50 agent
  steps even in float64), so trajectories are compared only up to the first ground contacts (2 agent steps,
  positions and orientations within 1e-2; fast: 2.0e-6) and then statistically over 24 random-action episodes of
  80 agent steps: mean returns within 3 standard errors (fast 5.32 against 5.33, standard error 0.32), and no
  velocity above twice dm_control's largest (fast 51.5 against 54.1). A solver that is too weak fails the
  velocity bound and the first 2 steps: iterations 2 / line search 4 reached a velocity of 230.8 against the bound
  108.2 and was 0.59 off after 2 steps, while its mean return stayed within 3 standard errors (7.43, standard
  error 1.01).
"""

from __future__ import annotations

import dm_reference
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc import envs


def _actions(task: str, n: int, steps: int, push: float = 0.0) -> np.ndarray:
    """(n, steps, nu) uniform random actions in [-1, 1]; ``push`` biases each episode's towards +1 or -1 (a random
    side per episode), e.g. to reach joint limits."""
    rng = np.random.default_rng(0)
    nu = dm_reference.load(task, 0).action_spec().shape[0]
    side = np.where(rng.random(n) < 0.5, 1.0, -1.0)[:, None, None]
    return np.clip(push * side + (1 - push) * rng.uniform(-1, 1, (n, steps, nu)), -1, 1)


def _dm_control_rollouts(task: str, qpos, qvel, actions, repeat: int = 2):
    """dm_control from each initial state, each action held for ``repeat`` control steps: (obs (n, steps, d),
    rewards (n, steps), summed over the repeats)."""
    env = dm_reference.load(task, 0)
    obs, rewards = [], []
    for q, v, episode in zip(qpos, qvel, actions, strict=True):
        env.reset()
        with env.physics.reset_context():
            env.physics.data.qpos[:], env.physics.data.qvel[:] = q, v
        for action in episode:
            reward = 0.0
            for _ in range(repeat):
                timestep = env.step(action)
                reward += timestep.reward
            obs.append(dm_reference.flat_obs(timestep))
            rewards.append(reward)
    shape = actions.shape[:2]
    return np.reshape(obs, (*shape, -1)), np.reshape(rewards, shape)


def _fast_rollouts(task: str, qpos, qvel, actions):
    """The fast profile (action repeat 2, float32) from the same states with the same actions: (clean obs (n,
    steps, d), rewards (n, steps)) in float64."""
    env = envs.make(task, physics="fast")

    def episode(q, v, acts):
        def body(state, action):
            state = env.step(state, action)
            return state, (state.clean_obs, state.reward)

        return jax.lax.scan(body, env.reset_to(q, v), acts)[1]

    obs, rewards = jax.jit(jax.vmap(episode))(*(jnp.asarray(x, jnp.float32) for x in (qpos, qvel, actions)))
    return np.asarray(obs, np.float64), np.asarray(rewards, np.float64)


def _both(task: str, n: int, steps: int, push: float = 0.0):
    qpos, qvel = dm_reference.initial_states(task, n, seed=0)
    actions = _actions(task, n, steps, push)
    return _dm_control_rollouts(task, qpos, qvel, actions), _fast_rollouts(task, qpos, qvel, actions)


@pytest.mark.parametrize("task,steps,tolerance", [("cartpole-swingup", 150, 1e-3), ("acrobot-swingup", 50, 2e-4)])
def test_fast_matches_dm_control_without_contacts(task, steps, tolerance):
    (obs_exact, rew_exact), (obs_fast, rew_fast) = _both(task, n=8, steps=steps, push=0.6)
    if task.startswith("cartpole"):
        assert np.abs(obs_exact[..., 0]).max() > 1.8  # the slider limit (1.8) was hit
    np.testing.assert_allclose(obs_fast, obs_exact, rtol=0, atol=tolerance)
    np.testing.assert_allclose(rew_fast, rew_exact, rtol=0, atol=tolerance)


def test_fast_walker_agrees_with_dm_control():
    n = 24
    (obs_exact, rew_exact), (obs_fast, rew_fast) = _both("walker-run", n, steps=80)  # the largest velocities come early
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
