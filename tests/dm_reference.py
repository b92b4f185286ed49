"""dm_control on the CPU as the independent reference for the MJX environments (float64)."""

from __future__ import annotations

import os

import numpy as np

os.environ.setdefault("MUJOCO_GL", "disable")


def load(task: str, seed: int):
    """`dm_control.suite.load` for an lnnmpc task name such as "cartpole-swingup-sparse"."""
    from dm_control import suite

    domain, _, name = task.partition("-")
    return suite.load(domain, name.replace("-", "_"), task_kwargs={"random": seed})


def flat_obs(timestep) -> np.ndarray:
    return np.concatenate([np.atleast_1d(v).ravel() for v in timestep.observation.values()])


def rollout(task: str, seed: int, actions: np.ndarray, extra_tasks=()):
    """Resets dm_control's env, then applies ``actions`` (T, nu).

    Returns:
      qpos0, qvel0 after reset; obs (T + 1, obs_dim) with the reset observation first; rewards {task: (T,)}
      for ``task`` and every task in ``extra_tasks`` (same domain, read off the same physics).
    """
    env = load(task, seed)
    others = {name: load(name, seed).task for name in extra_tasks}
    timestep = env.reset()
    physics = env.physics
    qpos, qvel = physics.data.qpos.copy(), physics.data.qvel.copy()
    obs = [flat_obs(timestep)]
    rewards = {name: [] for name in (task, *extra_tasks)}
    for action in actions:
        timestep = env.step(action)
        obs.append(flat_obs(timestep))
        rewards[task].append(timestep.reward)
        for name, other in others.items():
            rewards[name].append(other.get_reward(physics))
    return qpos, qvel, np.asarray(obs), {k: np.asarray(v, dtype=np.float64) for k, v in rewards.items()}


def initial_states(task: str, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n, nq) and (n, nv) post-reset physics states from dm_control's own initialisation."""
    env = load(task, seed)
    qpos, qvel = [], []
    for _ in range(n):
        env.reset()
        qpos.append(env.physics.data.qpos.copy())
        qvel.append(env.physics.data.qvel.copy())
    return np.asarray(qpos), np.asarray(qvel)
