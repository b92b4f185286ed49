"""The on-device training loop: chunks of agent steps (act -> env step -> replay insert -> update) in one scan.

All state of one seed is a :class:`TrainState` pytree; the host ``vmap``s every function over seeds and only
touches the state between chunks. The schedule (SPEC §1) is driven by the host with three compiled programs:
:func:`seed_chunk` (uniform random actions, no updates), :func:`update_burst` (as many updates as agent steps of
the seed phase) and :func:`train_chunk` (MPPI with exploration noise, ``num_envs`` updates per iteration so that
there is one update per agent step).

Replay records: the record at step t holds obs_t, the action a_t and the reward r_t it earned; the final
observation of an episode is its own record (action 0, reward 0), written on the iteration that resets the
environment (an iteration that takes no environment step; episodes have a fixed length, so all environments of
a seed reset together).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from lnnmpc import envs as envs_lib
from lnnmpc.agents.tdmpc2 import TDMPC2, AgentState
from lnnmpc.replay import ReplayState, replay_add, replay_init, replay_sample


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Static settings of the loop (the trainer's CLI builds it)."""

    num_envs: int = 1
    batch_size: int = 256
    replay_capacity: int = 100_300
    eval_episodes: int = 10

    def __post_init__(self):
        for name in ("num_envs", "batch_size", "replay_capacity", "eval_episodes"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


@struct.dataclass
class TrainState:
    """One seed's training state: agent, replay buffer, environments (num_envs,), planner warm start, RNG."""

    agent: AgentState
    replay: ReplayState
    env: Any
    plan_mean: jax.Array  # (num_envs, horizon, A)
    episode_return: jax.Array  # (num_envs,) return so far in the current episode
    key: jax.Array


class TrainingLoop:
    """Compiled pieces of training for one agent on one environment (vmap them over seeds)."""

    def __init__(self, agent: TDMPC2, env: envs_lib.Env, eval_env: envs_lib.Env, config: LoopConfig):
        self.agent, self.env, self.eval_env, self.config = agent, env, eval_env, config
        self.horizon = agent.config.planner.horizon

    # ------------------------------------------------------------------------------------------ init
    def init(self, key: jax.Array) -> TrainState:
        k_agent, k_env, k_loop = jax.random.split(key, 3)
        m, act_dim = self.config.num_envs, self.env.action_size
        record = {"obs": jnp.zeros((self.env.observation_size,)), "action": jnp.zeros((act_dim,)),
                  "reward": jnp.zeros(())}
        return TrainState(
            agent=self.agent.init(k_agent), replay=replay_init(record, self.config.replay_capacity, m),
            env=jax.vmap(self.env.reset)(jax.random.split(k_env, m)),
            plan_mean=jnp.zeros((m, self.horizon, act_dim)), episode_return=jnp.zeros((m,)), key=k_loop)

    # ------------------------------------------------------------------------------------------ steps
    def _env_step(self, ts: TrainState, action: jax.Array, key: jax.Array):
        """Records the transition, steps (or resets after the last step of an episode) every environment."""
        env = ts.env
        terminal = env.done  # (m,)
        action = jnp.where(terminal[:, None], 0.0, action)
        stepped = jax.vmap(self.env.step)(env, action)
        fresh = jax.vmap(self.env.reset)(jax.random.split(key, self.config.num_envs))
        reward = jnp.where(terminal, 0.0, stepped.reward)
        record = {"obs": env.obs, "action": action, "reward": reward}
        replay = replay_add(ts.replay, record, env.t == 0)
        new_env = jax.tree_util.tree_map(
            lambda a, b: jnp.where(terminal.reshape(terminal.shape + (1,) * (a.ndim - 1)), a, b), fresh, stepped)
        finished = jnp.where(terminal, ts.episode_return, jnp.nan)  # returns of episodes that just ended
        episode_return = jnp.where(terminal, 0.0, ts.episode_return + reward)
        return ts.replace(replay=replay, env=new_env, episode_return=episode_return), {
            "reward": reward, "episode_return": finished}

    def _update(self, ts: TrainState, key: jax.Array):
        k_sample, k_update = jax.random.split(key)
        records, valid = replay_sample(ts.replay, k_sample, self.config.batch_size, self.horizon + 1)
        agent, metrics = self.agent.update(ts.agent, records, k_update)
        # Keep the old agent if the buffer had no valid window yet (never after the seed phase).
        agent = jax.tree_util.tree_map(lambda new, old: jnp.where(valid.all(), new, old), agent, ts.agent)
        return ts.replace(agent=agent), metrics

    def seed_chunk(self, ts: TrainState, length: int) -> tuple[TrainState, dict]:
        """``length`` iterations of uniform random actions (no updates)."""
        def body(ts, _):
            key, k_act, k_env = jax.random.split(ts.key, 3)
            action = jax.random.uniform(k_act, (self.config.num_envs, self.env.action_size), minval=-1, maxval=1)
            return self._env_step(ts.replace(key=key), action, k_env)

        return jax.lax.scan(body, ts, None, length=length)

    def update_burst(self, ts: TrainState, num_updates: int) -> tuple[TrainState, dict]:
        """``num_updates`` updates in a row (after the seed phase)."""
        def body(ts, _):
            key, k_update = jax.random.split(ts.key)
            return self._update(ts.replace(key=key), k_update)

        return jax.lax.scan(body, ts, None, length=num_updates)

    def train_chunk(self, ts: TrainState, length: int) -> tuple[TrainState, dict]:
        """``length`` iterations of planning with exploration, an environment step and num_envs updates."""
        m = self.config.num_envs

        def body(ts, _):
            key, k_act, k_env, k_update = jax.random.split(ts.key, 4)
            act = jax.vmap(lambda obs, mean, k, first: self.agent.act(ts.agent, obs, mean, k, explore=True,
                                                                      first_step=first))
            action, plan_mean = act(ts.env.obs, ts.plan_mean, jax.random.split(k_act, m), ts.env.t == 0)
            ts, out = self._env_step(ts.replace(key=key, plan_mean=plan_mean), action, k_env)
            ts, metrics = jax.lax.scan(lambda ts, k: self._update(ts, k), ts, jax.random.split(k_update, m))
            return ts, {**out, **jax.tree_util.tree_map(lambda x: x[-1], metrics)}

        return jax.lax.scan(body, ts, None, length=length)

    # -------------------------------------------------------------------------------------- evaluate
    def evaluate(self, agent: AgentState, key: jax.Array) -> jax.Array:
        """Returns (eval_episodes,) of deterministic MPPI episodes, run in parallel, each with its own seed."""
        n, env = self.config.eval_episodes, self.eval_env
        k_reset, k_act = jax.random.split(key)
        state = jax.vmap(env.reset)(jax.random.split(k_reset, n))
        mean = jnp.zeros((n, self.horizon, env.action_size))

        def body(carry, k):
            state, mean, total = carry
            act = jax.vmap(lambda obs, m, kk, first: self.agent.act(agent, obs, m, kk, explore=False,
                                                                    first_step=first))
            action, mean = act(state.obs, mean, jax.random.split(k, n), state.t == 0)
            state = jax.vmap(env.step)(state, action)
            return (state, mean, total + state.reward), None

        keys = jax.random.split(k_act, env.episode_length)
        (_, _, total), _ = jax.lax.scan(body, (state, mean, jnp.zeros((n,))), keys)
        return total
