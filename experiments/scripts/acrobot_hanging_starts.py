"""How an acrobot policy does from the hardest initial states: both links hanging down, at rest.

    python experiments/scripts/acrobot_hanging_starts.py RUN [--episodes 8] [--sigma 0.1] [--checkpoint STEP]
        [--actor planner|prior] [--planner KEY=VALUE ...] [--out CSV]

dm_control's acrobot-swingup starts each episode at joint angles drawn uniformly from [-pi, pi) and at rest; the
final policies of the acrobot runs score least on the episodes that start hanging down (dm_control initial states
4 and 9 of seed 0: shoulder 168 and -176 degrees, elbow 17 and 1). This plays a run's seed-0 policy (MJX, the
evaluation protocol: MPPI without exploration noise, :func:`lnnmpc.analysis.rollout.rollout`) from such starts
only: shoulder pi + N(0, sigma^2), elbow N(0, sigma^2), velocities zero (the start replaces
``Env.initial_qpos_qvel`` for this process before anything traces a reset, since traced resets are cached). Per
episode it reports the return, the highest the tip got above the shoulder (2.0: on the target; 0: level with the
shoulder; -2.0: hanging) and the first agent step with the tip above the shoulder (also in seconds of simulated
time, which compare across action repeats). ``--actor prior`` plays the
policy prior alone and ``--planner`` plans with other MPPI settings, as ``lnnmpc.train.cli eval`` does. Writes
the rows to CSV (default <run>/analysis/<step>/hanging_starts.csv) and prints a summary.
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np


def hanging_init(sigma: float):
    """An ``Env.initial_qpos_qvel`` replacement: both links down (shoulder pi, elbow 0) plus N(0, sigma^2) noise."""

    def init(self, key):
        noise = sigma * jax.random.normal(key, (2,))
        qpos = jnp.array([jnp.pi, 0.0]) + noise
        return jnp.mod(qpos + jnp.pi, 2 * jnp.pi) - jnp.pi, jnp.zeros((self.mj_model.nv,))

    return init


def play(policy, agent, episodes: int) -> dict[str, np.ndarray]:
    """Seed 0's deterministic episodes acted by ``agent`` (:func:`lnnmpc.analysis.rollout.rollout`, key 0); per
    episode: the return, the highest tip height above the shoulder, the first agent step above it (-1: never) and
    the start's joint angles."""
    from lnnmpc.analysis.acrobot import tip_positions
    from lnnmpc.analysis.rollout import rollout

    records = rollout(agent, policy.seed_state(0), policy.loop.eval_env, jax.random.key(0), episodes)
    tips, shoulder, _, _ = tip_positions(records["qpos"])
    height = tips[..., 2] - shoulder[2]  # (E, T)
    above = height > 0
    first = np.where(above.any(axis=1), above.argmax(axis=1), -1)
    return {"return": records["reward"].sum(axis=1), "max_tip_height": height.max(axis=1),
            "first_step_above": first, "start_shoulder": records["qpos"][:, 0, 0],
            "start_elbow": records["qpos"][:, 0, 1]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--sigma", type=float, default=0.1, help="radians of noise on the hanging start")
    p.add_argument("--checkpoint", type=int, default=None)
    p.add_argument("--actor", default="planner", choices=("planner", "prior"))
    p.add_argument("--planner", action="append", default=[], metavar="KEY=VALUE", help="MPPI setting, repeatable")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.episodes < 1 or args.sigma < 0:
        print(f"--episodes must be >= 1 and --sigma >= 0, got {args.episodes} and {args.sigma}", file=sys.stderr)
        return 2
    from lnnmpc.agents.actor import with_actor
    from lnnmpc.envs.env import Env
    from lnnmpc.train import runfolder
    from lnnmpc.train.config import ConfigError, parse_overrides
    from lnnmpc.train.evaluate import load_policy, with_planner

    if not runfolder.saved_config(args.run).task.startswith("acrobot"):
        print(f"{args.run} is no acrobot run", file=sys.stderr)
        return 2
    Env.initial_qpos_qvel = hanging_init(args.sigma)  # before loading: a reset traced there would be cached
    policy = load_policy(args.run, args.checkpoint)
    try:
        agent = with_actor(with_planner(policy.loop.agent, parse_overrides(args.planner, "--planner")), args.actor)
    except (ConfigError, ValueError) as error:
        print(error, file=sys.stderr)
        return 2
    played = play(policy, agent, args.episodes)
    off = np.abs(np.abs(played["start_shoulder"]) - np.pi)
    if np.any(off > 6 * args.sigma + 1e-3):
        print(f"the episodes did not start hanging (shoulder {played['start_shoulder']}): a reset traced before the "
              "start was replaced?", file=sys.stderr)
        return 1
    setting = " ".join([args.actor, *args.planner])
    rows = [{"env_step": policy.checkpoint, "sigma": args.sigma, "setting": setting, "episode": e,
             **{k: float(v[e]) for k, v in played.items()}} for e in range(args.episodes)]
    seconds_per_step = policy.loop.eval_env.agent_timestep
    for row in rows:
        above = row["first_step_above"]
        row["first_seconds_above"] = above * seconds_per_step if above >= 0 else -1.0
    ret, top, first = played["return"], played["max_tip_height"], played["first_step_above"]
    starts = zip(played["start_shoulder"], played["start_elbow"], strict=True)
    print(f"hanging starts (sigma {args.sigma}), {setting}: return {ret.mean():.1f} +- {ret.std():.1f} (episodes "
          f"{' '.join(f'{r:.0f}' for r in ret)}); tip above the shoulder in {int((top > 0).sum())} of "
          f"{args.episodes} (first at agent steps {' '.join(str(int(f)) for f in first)}, "
          f"{seconds_per_step:g} s each); "
          f"highest tip {' '.join(f'{h:.2f}' for h in top)}; starts (shoulder, elbow) "
          f"{' '.join(f'({a:.2f}, {b:.2f})' for a, b in starts)}")
    out = args.out or os.path.join(args.run, "analysis", str(policy.checkpoint), "hanging_starts.csv")
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    runfolder.write_csv(out, list(rows[0]), rows)
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
