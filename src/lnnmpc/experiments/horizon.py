"""Evaluation of a trained run with another planning horizon, and the time of one planning decision (Fig. 5.19).

The world model does not depend on the planning horizon, so a checkpoint trained with H_plan = 10 is evaluated
with any H_plan by rebuilding the agent with the ``plan_horizon`` planner override
(:func:`lnnmpc.train.evaluate.with_planner`, what ``eval --planner`` uses) and restoring the same parameters.
"""

from __future__ import annotations

import os
import time

import jax
import numpy as np

from lnnmpc.train import runfolder
from lnnmpc.train.config import obs_tag, parse_obs, require_int
from lnnmpc.train.evaluate import load_policy, mjx_evaluator, with_planner
from lnnmpc.train.setup import config_env


def planner_times(agent, state, env, key: jax.Array, calls: int = 30) -> np.ndarray:
    """Wall time in ms of ``calls`` deterministic planning decisions (one environment, compiled first).

    ``state``: one seed's agent state (no seed axis). Each call is timed to completion (``block_until_ready``).
    """
    k_reset, k_act = jax.random.split(key)
    env_state = jax.jit(env.reset)(k_reset)
    act = jax.jit(lambda s, c, o, dt, k: agent.act(s, c, o, dt, k, explore=False, first_step=False))
    carry = agent.initial_carry()
    for _ in range(2):  # compile for the initial carry and for the carry act returns (its types may differ)
        action, carry = act(state, carry, env_state.obs, env_state.dt, k_act)
    jax.block_until_ready(action)
    times = []
    for k in jax.random.split(k_act, calls):
        start = time.perf_counter()
        action, carry = act(state, carry, env_state.obs, env_state.dt, k)
        jax.block_until_ready(action)
        times.append(1000 * (time.perf_counter() - start))
    return np.asarray(times)


def evaluate_horizon(run: str, horizon: int, *, obs: str | dict | None = None, episodes: int = 10, seed: int = 0,
                     checkpoint: int | None = None, out: str | None = None, timing_calls: int = 30) -> str:
    """Plays ``episodes`` deterministic episodes per seed with planning horizon ``horizon``; writes a CSV
    (env_step, seed, episode, return, horizon, obs, planner_ms: one timed decision per row) and returns its path
    (default ``<run>/evals/horizon<H>-<obs tag>-<step>.csv``)."""
    require_int("horizon", horizon, 1)
    policy = load_policy(run, checkpoint)
    config = policy.config
    options = dict(config.eval_obs) if obs is None else parse_obs(obs)
    env = config_env(config, options)
    agent = with_planner(policy.loop.agent, {"plan_horizon": horizon})
    key = jax.random.key(seed)
    returns = mjx_evaluator(agent, env, episodes, config.seeds)(policy.agent_state, key)
    first_seed = policy.seed_state(0)
    times = planner_times(agent, first_seed, env, jax.random.fold_in(key, 1), calls=max(timing_calls, returns.size))
    path = out or os.path.join(run, "evals", f"horizon{horizon}-{obs_tag(options)}-{policy.checkpoint}.csv")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if os.path.exists(path):
        os.remove(path)
    rows = [{"env_step": policy.checkpoint, "seed": s, "episode": e, "return": float(returns[s, e]),
             "horizon": horizon, "obs": obs_tag(options), "planner_ms": float(times[s * returns.shape[1] + e])}
            for s in range(returns.shape[0]) for e in range(returns.shape[1])]
    runfolder.append_csv(path, rows)
    return path
