"""What a cartpole-swingup-sparse seed that has never seen a reward executes in training: its exploring episodes.

    .venv/bin/python experiments/scripts/stuck_seed_exploration.py RUN --seed I [--episodes 8] [--out CSV]

Loads seed I of a trained run (``RUN/policy.npz``, :func:`lnnmpc.train.evaluate.load_policy`) and plays
``--episodes`` MJX episodes acting as the trainer does between updates (``act(..., explore=True)``: MPPI plus its
exploration noise), once with TD-MPC2's white noise and once with an episode-long pink sequence per episode
(``train --explore-noise-beta 1``), and once without noise (the evaluation protocol), from the same initial
states; the ``*-floor*`` kinds put a floor under the noise's scale (``--set explore_min_std=F``: max(std, F) in
place of the planner's std). ``--kinds`` picks some. Prints per kind the share of episodes with any reward, the
mean return, the mean |action|, the mean over episodes of |the episode's mean action| (a planner pushing one way
all episode: near 1), the actions' lag-1 autocorrelation, and :func:`lnnmpc.analysis.cartpole.episode_stats`
(turns, mean |cart|).

The question: when a seed's reward and value heads have been trained on zeros only (RESULTS.md [54]: every training
episode 0 for 100K steps), is its planner still exploring at the std ``random_exploration_sparse.py`` and
``flat_planner_exploration_sparse.py`` assume, or has it settled on a fixed behaviour (the top-k selection follows
whatever smooth tilt the near-zero Q heads have, whatever their scale)?
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.agents.exploration import colored_noise
from lnnmpc.analysis.cartpole import episode_stats
from lnnmpc.train.evaluate import load_policy
from lnnmpc.train.loop import evaluation_keys, evaluation_step_keys, stacked_initial_carry

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from random_exploration_sparse import lag1_autocorrelation, save_rows  # noqa: E402

# kind: (noise: None / "white" / "pink", floor of the noise's scale, MPPIConfig.explore_min_std)
KINDS = {"none": (None, 0.0), "white": ("white", 0.0), "pink": ("pink", 0.0), "pink-floor0.5": ("pink", 0.5),
         "pink-floor1": ("pink", 1.0), "white-floor1": ("white", 1.0)}


def with_noise_floor(agent, floor: float):
    """``agent`` rebuilt with ``explore_min_std=floor`` (the same parameters fit it: the planner has none)."""
    config = agent.config
    return type(agent)(dataclasses.replace(config, planner=dataclasses.replace(config.planner,
                                                                               explore_min_std=floor)))


def exploring_episodes(agent, agent_state, env, key, episodes: int, kind: str | None):
    """(rewards (E, T), qpos (E, T, 2), actions (E, T, A)) of ``episodes`` episodes acting with noise ``kind``
    (None: no noise, "white" or "pink")."""
    k_reset, k_act = evaluation_keys(key, episodes)
    steps = env.episode_length
    pink = colored_noise(jax.random.fold_in(key, 7), 1.0, steps, (episodes, env.action_size))

    def body(loop_carry, xs):
        s, carry = loop_carry
        t, noise_t = xs

        def act(c, o, dt, kk, f, n):
            explore_noise = n if kind == "pink" else None
            return agent.act(agent_state, c, o, dt, kk, explore=kind is not None, first_step=f,
                             explore_noise=explore_noise)

        action, carry = jax.vmap(act)(carry, s.obs, s.dt, evaluation_step_keys(k_act, t), s.t == 0, noise_t)
        nxt = jax.vmap(env.step)(s, action)
        return (nxt, carry), (nxt.reward, s.physics.qpos, action)

    @jax.jit
    def run():
        init = (jax.vmap(env.reset)(k_reset), stacked_initial_carry(agent, episodes))
        return jax.lax.scan(body, init, (jnp.arange(steps), pink))[1]

    rewards, qpos, actions = (np.swapaxes(np.asarray(x), 0, 1) for x in run())
    return rewards, qpos, actions


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--seed", type=int, required=True, help="which trained seed of the run")
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=list(KINDS))
    p.add_argument("--out", default=None, help="CSV path")
    args = p.parse_args(argv)
    policy = load_policy(args.run)
    state = policy.seed_state(args.seed)
    env = policy.loop.env
    rows = []
    for kind in args.kinds:
        noise, floor = KINDS[kind]
        agent = with_noise_floor(policy.loop.agent, floor) if floor else policy.loop.agent
        rewards, qpos, actions = exploring_episodes(agent, state, env, jax.random.key(0), args.episodes, noise)
        returns = rewards.sum(axis=1)
        stats = episode_stats(qpos)
        rows.append({"run": args.run, "env_step": policy.checkpoint, "seed": args.seed, "noise": kind,
                     "episodes": args.episodes, "share_with_reward": float((returns > 0).mean()),
                     "mean_return": float(returns.mean()), "mean_abs_action": float(np.abs(actions).mean()),
                     "abs_episode_mean_action": float(np.abs(actions[..., 0].mean(axis=1)).mean()),
                     "lag1_autocorrelation": lag1_autocorrelation(actions[..., 0]),
                     "turns": float(stats["turns"].mean()),
                     "mean_abs_cart": float(stats["mean_abs_cart"].mean())})
        r = rows[-1]
        print(f"{kind:13s} with reward {r['share_with_reward']:.3f}  return {r['mean_return']:6.2f}  "
              f"|a| {r['mean_abs_action']:.2f}  |episode mean a| {r['abs_episode_mean_action']:.2f}  "
              f"lag-1 {r['lag1_autocorrelation']:.2f}  turns {r['turns']:.2f}  |cart| {r['mean_abs_cart']:.2f}",
              flush=True)
    if args.out:
        save_rows(rows, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
