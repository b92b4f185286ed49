"""What a trained agent's Q heads promise against what its own deterministic episodes pay, seed by seed.

    python experiments/scripts/value_vs_return.py <run folder> [--checkpoint STEP] [--episodes 1] [--steps 200]

Plays the trainer's evaluation episodes (MPPI, no exploration noise; :func:`lnnmpc.analysis.rollout.rollout`) with
each seed of a run and compares, over the first ``--steps`` agent steps of each episode, the Q heads' mean value
of the action taken, Q(z_t, a_t), with the discounted return the episode actually paid from t on,
G_t = sum_k gamma^k r_{t+k} (to the episode's end: with 500-step episodes and gamma 0.99, G_t for t <= 200 misses
less than 5% of the tail). A seed whose Q stays far above its G is planning on values its episodes never collect
(an over-estimate the planner acts on); a seed whose Q tracks its G has a calibrated critic. The reward head's
prediction for the same (z_t, a_t), against the reward paid, over the same steps, tells whether the world model
itself expects rewards the episode does not pay (a seed balancing outside the sparse region); the Q heads' spread
(largest minus smallest head, mean over the steps) tells whether the heads disagree where the critic is wrong, which
a pessimistic planning value (the minimum of the heads) would penalise. Prints one row per
seed and writes it to ``<run>/analysis/<step>/value_vs_return.csv`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def seed_rows(run: str, checkpoint: int | None, episodes: int, steps: int) -> list[dict]:
    import jax
    import jax.numpy as jnp

    from lnnmpc.agents.returns import lambda_returns
    from lnnmpc.analysis.episodes import seed_rollouts, seeds_progress
    from lnnmpc.train.evaluate import load_policy

    policy = load_policy(run, checkpoint)
    agent = policy.loop.agent
    heads = jnp.arange(agent.config.model.num_q)
    # every head's Q (heads,) and the reward head's prediction () of one (z, a), vmapped over the recorded steps
    heads_and_reward = jax.vmap(lambda params, z, a: (agent._q_values(params, z, a, heads),
                                                      agent._predicted_reward(params, z, a)), in_axes=(None, 0, 0))
    rows = []
    for seed, state, records in seed_rollouts(policy, episodes, progress=seeds_progress(episodes)):
        z, action = records["latent"], records["action"]
        steps_z, steps_a = z.reshape(-1, z.shape[-1]), action.reshape(-1, action.shape[-1])  # (E * T, ...)
        q_heads, r_hat = heads_and_reward(state.params, steps_z, steps_a)
        q_heads = np.asarray(q_heads).reshape(*z.shape[:2], -1)  # (E, T, heads)
        r_hat = np.asarray(r_hat).reshape(z.shape[:2])
        q, spread = q_heads.mean(axis=-1), q_heads.max(axis=-1) - q_heads.min(axis=-1)
        # G_t to the episode's end: TD(1) targets with no value after the last step
        reward = jnp.asarray(records["reward"]).T  # time-major (T, E)
        g = np.asarray(lambda_returns(reward, jnp.zeros_like(reward), agent.config.gamma, 1.0)).T
        rows.append({"env_step": policy.checkpoint, "seed": seed, "episodes": episodes, "steps": steps,
                     "return": float(records["reward"].sum(axis=1).mean()),
                     "q_mean": float(q[:, :steps].mean()), "g_mean": float(g[:, :steps].mean()),
                     "q_minus_g": float((q[:, :steps] - g[:, :steps]).mean()),
                     "q_start": float(q[:, 0].mean()), "g_start": float(g[:, 0].mean()),
                     "q_head_spread": float(spread[:, :steps].mean()),
                     "reward_hat_mean": float(r_hat[:, :steps].mean()),
                     "reward_mean": float(records["reward"][:, :steps].mean())})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--checkpoint", type=int, default=None)
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--steps", type=int, default=200, help="agent steps from each episode's start compared")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.episodes < 1 or args.steps < 1:
        print(f"--episodes and --steps must be >= 1, got {args.episodes} and {args.steps}", file=sys.stderr)
        return 2
    rows = seed_rows(args.run, args.checkpoint, args.episodes, args.steps)
    from lnnmpc.analysis.episodes import SEED_COLUMNS, markdown_table
    from lnnmpc.train import runfolder

    out = args.out or os.path.join(args.run, "analysis", str(rows[0]["env_step"]))
    os.makedirs(out, exist_ok=True)
    fields = list(rows[0])
    runfolder.write_csv(os.path.join(out, "value_vs_return.csv"), fields, rows)
    print(markdown_table(rows, (*SEED_COLUMNS, ("Q(z_t, a_t)", "q_mean", ".1f"), ("G_t", "g_mean", ".1f"),
                                ("Q - G", "q_minus_g", "+.1f"), ("Q at t = 0", "q_start", ".1f"),
                                ("G at t = 0", "g_start", ".1f"), ("heads' spread", "q_head_spread", ".1f"),
                                ("predicted reward", "reward_hat_mean", ".3f"), ("reward", "reward_mean", ".3f"))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
