"""What an MPPI planner whose value is flat executes on cartpole-swingup-sparse, with white and pink exploration noise.

    .venv/bin/python experiments/scripts/flat_planner_exploration_sparse.py [--episodes 64] [--out CSV]

A seed that has seen no reward yet trains its reward and Q heads on zeros only (RESULTS.md [54]: reward loss exactly
0 for 120K steps), so every candidate sequence scores the same up to rounding and MPPI ranks them at random. This
script runs the trainer's own :func:`lnnmpc.agents.mppi.mppi_plan` (TD-MPC2's defaults: 512 samples, 24 of them
from the policy prior, 64 elites, 6 iterations, horizon 3, the mean warm-started from the previous step) on a
stand-in model whose reward and value are 1e-6-sized pseudo-random functions of the action (a random ranking) and
whose policy prior is a squashed Gaussian at the largest std (log std 2, what a prior trained on zero rewards
tends to), then plays the executed actions in MJX episodes from the same initial states as
``random_exploration_sparse.py`` and counts the episodes that reach the rewarded region. Executed actions:

* ``white``: a random elite's first action plus the final std times a fresh N(0, 1) draw (TD-MPC2, the default);
* ``pink``: the same with step t of an episode-long pink sequence in place of the draw (``train
  --explore-noise-beta 1``);
* ``mean-pink``: the final MPPI mean's first action plus the std times the pink sample (no elite draw).

Also prints the mean final std of the first action and the executed actions' lag-1 autocorrelation (white ~0,
pink near 1). The question: does the elite draw, white at every step, drown the pink noise?
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc import envs
from lnnmpc.agents.exploration import colored_noise
from lnnmpc.agents.mppi import MPPIConfig, PlanningModel, mppi_plan

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from random_exploration_sparse import lag1_autocorrelation, outcome_columns, play, save_rows  # noqa: E402

KINDS = ("white", "pink", "mean-pink")
TINY = 1e-6


def flat_model(action_dim: int) -> PlanningModel:
    """A model whose scores are tiny pseudo-random functions of (z, a): MPPI ranks its samples at random. The
    latent z is one float (a per-step random offset); the prior samples tanh(N(0, e^2))."""
    w_reward = jnp.linspace(1.0, 2.0, action_dim)
    w_value = jnp.linspace(3.0, 4.0, action_dim)

    def dynamics(z, a):
        return z + 0.1 * jnp.dot(a, w_reward)

    def reward(z, a):
        return TINY * jnp.sin(1e4 * (z + jnp.dot(a, w_reward)))

    def value(z, a, key):
        return TINY * jnp.sin(1e4 * (z + jnp.dot(a, w_value)) + jax.random.uniform(key))

    def policy(z, key):
        return jnp.tanh(jnp.exp(2.0) * jax.random.normal(key, (action_dim,)))

    return PlanningModel(dynamics=dynamics, reward=reward, value=value, policy=policy)


def planner_actions(kind: str, key: jax.Array, episodes: int, steps: int, action_dim: int,
                    config: MPPIConfig) -> tuple[np.ndarray, np.ndarray]:
    """(steps, episodes, action_dim) executed actions of one kind and (steps, episodes) the final std[0]."""
    model = flat_model(action_dim)
    k_noise, k_plan = jax.random.split(key)
    pink = colored_noise(k_noise, 1.0, steps, (episodes, action_dim))  # (steps, episodes, A)

    def one_step(carry, xs):
        prev_mean = carry
        t, pink_t, k = xs
        keys = jax.random.split(k, episodes)
        z0 = jax.vmap(lambda kk: jax.random.uniform(kk))(jax.random.split(jax.random.fold_in(k, 1), episodes))
        noise = None if kind == "white" else pink_t
        plan = jax.vmap(lambda z, m, kk, n: mppi_plan(config, model, z, m, kk, explore=True, first_step=t == 0,
                                                      explore_noise=n),
                        in_axes=(0, 0, 0, None if noise is None else 0))
        action, mean, info = plan(z0, prev_mean, keys, noise)
        if kind == "mean-pink":
            action = jnp.clip(mean[:, 0] + info["std"][:, 0] * pink_t, -1.0, 1.0)
        return mean, (action, info["std"][:, 0, 0])

    init = jnp.zeros((episodes, config.horizon, action_dim))
    xs = (jnp.arange(steps), pink, jax.random.split(k_plan, steps))
    _, (actions, std0) = jax.jit(lambda i, x: jax.lax.scan(one_step, i, x))(init, xs)
    return np.asarray(actions), np.asarray(std0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="CSV path")
    args = p.parse_args(argv)
    env = envs.make("cartpole-swingup-sparse")
    steps = env.episode_length
    keys = jax.random.split(jax.random.key(args.seed), args.episodes)
    config = MPPIConfig()
    rows = []
    for kind in KINDS:
        actions, std0 = planner_actions(kind, jax.random.key(1000 + args.seed), args.episodes, steps,
                                        env.action_size, config)
        rewards, qpos = play(env, keys, actions)
        rows.append({"kind": kind, "episodes": args.episodes, **outcome_columns(rewards, qpos),
                     "mean_std0": float(std0.mean()), "mean_abs_action": float(np.abs(actions).mean()),
                     "lag1_autocorrelation": lag1_autocorrelation(actions[..., 0].T)})
        r = rows[-1]
        print(f"{kind:9s} episodes with reward {r['share_with_reward']:.3f}  mean return {r['mean_return']:7.2f}  "
              f"turns {r['turns']:.2f}  std0 {r['mean_std0']:.2f}  |a| {r['mean_abs_action']:.2f}  "
              f"lag-1 autocorrelation {r['lag1_autocorrelation']:.2f}")
    if args.out:
        save_rows(rows, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
