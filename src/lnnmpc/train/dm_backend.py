"""Acting on the original dm_control simulator (CPU): the policy-transfer check of SPEC §2 and ``make video``.

Episodes run on ``dm_control.suite.load(domain, task)`` environments, stepped from Python, while the agent
acts through the same protocol as in training (``agent.act`` with its acting carry, deterministic), all seeds
and episodes in one jitted ``vmap``-ed call per decision. The observation pipeline is the MJX environment's:
dm_control's observation dict flattened in its key order, cast to float32, the kept dimensions
(``remove_vel``), then the corruptions of :mod:`lnnmpc.envs.corruptions` (noise, flicker, delay with its Δt),
applied every agent step. An agent step applies the action for ``action_repeat`` (2) control steps and sums
the rewards, so an episode is 500 decisions and its return is in [0, 1000].
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.envs import Env
from lnnmpc.envs.corruptions import corruption_reset, corruption_step
from lnnmpc.train.loop import stacked_initial_carry


def load_dm_control(env: Env, seed: int):
    """``dm_control.suite.load`` for an lnnmpc environment's task, seeded (``task_kwargs={"random": seed}``)."""
    from dm_control import suite

    return suite.load(env.spec.domain, env.spec.task, task_kwargs={"random": seed})


def flat_observation(timestep, kept: np.ndarray) -> np.ndarray:
    """dm_control's observation dict flattened in its key order, float32, restricted to the kept dimensions."""
    flat = np.concatenate([np.atleast_1d(value).ravel() for value in timestep.observation.values()])
    return flat.astype(np.float32)[kept]


def _corruption_fns(env: Env):
    config = env.corruption
    reset = jax.jit(jax.vmap(lambda key, obs: corruption_reset(config, key, obs)))
    step = jax.jit(jax.vmap(lambda state, key, t, obs: corruption_step(config, state, key, t, obs)))
    return reset, step


def _act_fn(agent: Any) -> Callable:
    """act for (seeds, episodes): agent states carry the seed axis, everything else (seeds, episodes, ...)."""
    def one(state, carry, obs, dt, key, first):
        return agent.act(state, carry, obs, dt, key, explore=False, first_step=first)

    per_seed = jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0))
    return jax.jit(jax.vmap(per_seed))


def episode_keys(key: jax.Array, seed_ids, episodes: int) -> jax.Array:
    """One key per (seed, episode), (len(seed_ids) * episodes,) seed-major: ``fold_in(fold_in(key, seed id),
    episode)``, so an episode's randomness does not depend on how many episodes or seeds play beside it."""
    per_seed = lambda s: jax.vmap(lambda e: jax.random.fold_in(jax.random.fold_in(key, s), e))(  # noqa: E731
        jnp.arange(episodes))
    return jax.vmap(per_seed)(jnp.asarray(seed_ids, jnp.int32)).reshape(-1)


@jax.jit
def _split_each(keys: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Each of the (N,) keys split in three: three (N,) key arrays."""
    split = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
    return split[:, 0], split[:, 1], split[:, 2]


def episode_tasks(env: Env, seed: int, episodes: int) -> list:
    """One seeded dm_control task per episode, as :func:`run_episodes` plays them: episode e's drawn with
    ``seed + e`` (its initial state is the task's after ``reset()``)."""
    return [load_dm_control(env, seed + e) for e in range(episodes)]


def run_episodes(env: Env, agent: Any, agent_states: Any, episodes: int, key: jax.Array, *, seed: int = 0,
                 seed_ids: list[int] | None = None,
                 on_step: Callable[[int, int, int, Any, float], None] | None = None,
                 progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Deterministic episodes of every seed's policy on dm_control; returns returns (seeds, episodes).

    Args:
      env: the lnnmpc environment whose task, action repeat and corruptions to reproduce.
      agent, agent_states: the agent and its state with a leading seed axis.
      key: randomness of the planner and the corruptions, one stream per episode (:func:`episode_keys`).
        seed: dm_control's initial-state seed (episode e of every seed policy starts from the same dm_control
        state, drawn with ``seed + e``).
      seed_ids: the run's seed index of each row of ``agent_states`` (default 0, 1, ...): a policy sliced out of a
        run (``make video``) plays episode e as its seed played it among all seeds (``make eval``).
      on_step: called as ``on_step(row, episode, agent_steps_done, physics, episode_return)`` after every agent
        step (``row`` of ``agent_states``; e.g. to render frames).
      progress: called as ``progress(agent_steps_done, episode_length)`` after every agent step of all episodes.
    """
    seeds = jax.tree_util.tree_leaves(agent_states)[0].shape[0]
    seed_ids = list(range(seeds)) if seed_ids is None else list(seed_ids)
    if len(seed_ids) != seeds:
        raise ValueError(f"seed_ids has {len(seed_ids)} entries for {seeds} seed(s) of agent states")
    n = (seeds, episodes)
    sims = [episode_tasks(env, seed, episodes) for _ in range(seeds)]
    timesteps = [[sim.reset() for sim in row] for row in sims]
    obs = np.stack([[flat_observation(ts, env.kept) for ts in row] for row in timesteps])
    k_corrupt, k_act, _ = _split_each(episode_keys(key, seed_ids, episodes))
    corrupt_reset, corrupt_step = _corruption_fns(env)
    cstate, delivered, dt = corrupt_reset(k_corrupt, jnp.asarray(obs.reshape(seeds * episodes, -1)))
    carry = stacked_initial_carry(agent, *n)
    act = _act_fn(agent)
    totals = np.zeros(n)
    for t in range(env.episode_length):
        k_act, k_step, k_obs = _split_each(k_act)
        action, carry = act(agent_states, carry, delivered.reshape(*n, -1), dt.reshape(n), k_step.reshape(n),
                            jnp.full(n, t == 0))
        action = np.asarray(action, dtype=np.float64)
        for s in range(seeds):
            for e in range(episodes):
                for _ in range(env.action_repeat):
                    timesteps[s][e] = sims[s][e].step(action[s, e])
                    totals[s, e] += timesteps[s][e].reward or 0.0
                if on_step is not None:
                    on_step(s, e, t + 1, sims[s][e].physics, totals[s, e])
        obs = np.stack([[flat_observation(ts, env.kept) for ts in row] for row in timesteps])
        cstate, delivered, dt = corrupt_step(cstate, k_obs, jnp.full(seeds * episodes, t + 1, jnp.int32),
                                             jnp.asarray(obs.reshape(seeds * episodes, -1)))
        if progress is not None:
            progress(t + 1, env.episode_length)
    return totals
