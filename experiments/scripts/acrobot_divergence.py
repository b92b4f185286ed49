"""How fast does a one-ulp difference grow in acrobot-swingup under the seed phase's random actions?

    PYTHONPATH=src python experiments/scripts/acrobot_divergence.py [--starts 16] [--agent-steps 250]
        [--action-repeat 4] [--out PREFIX]

RESULTS.md [92] found two launches of one command on one GPU apart at their first evaluation; the GPU sums MJX's
colliding scatter-adds in no fixed order, so two launches can differ by round-off in their first physics steps.
This measures, on this machine's JAX device, what such a difference becomes: for each of ``--starts`` starts drawn
from dm_control's initial-state distribution, the episode is played twice under the same uniform random actions
(the seed phase's), once from the start and once with the first joint angle moved by one float32 ulp
(``jnp.nextafter``); per agent step the largest absolute difference between the two clean observations. Prints the
median and the largest over starts at a few agent steps, the first agent step at which each passes 1e-3 and 0.1,
and how many starts' two plays ended identical (the ulp rounded away); ``--out PREFIX`` writes ``PREFIX.csv``
(agent_step, median, q25, q75, max) and ``PREFIX.png`` (log scale, zero drawn at 1e-10).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def divergence(starts: int, agent_steps: int, action_repeat: int, seed: int = 0) -> np.ndarray:
    """(starts, agent_steps) largest absolute difference between the clean observations of the two plays of each
    start (see the module docstring), after each agent step."""
    import jax
    import jax.numpy as jnp

    from lnnmpc.envs import make

    env = make("acrobot-swingup", action_repeat=action_repeat)
    k_start, k_act = jax.random.split(jax.random.key(seed))
    qpos, qvel = jax.vmap(env.initial_qpos_qvel)(jax.random.split(k_start, starts))
    nudged = qpos.at[:, 0].set(jnp.nextafter(qpos[:, 0], jnp.inf))
    actions = jax.random.uniform(k_act, (agent_steps, starts, env.action_size), minval=-1.0, maxval=1.0)

    @jax.jit
    def play(qpos, qvel, actions):  # (starts, nq), (starts, nv), (T, starts, A) -> (T, starts, obs)
        def one(q, v, acts):
            def step(state, action):
                state = env.step(state, action)
                return state, state.clean_obs
            return jax.lax.scan(step, env.reset_to(q, v), acts)[1]
        return jax.vmap(one, in_axes=(0, 0, 1), out_axes=1)(qpos, qvel, actions)

    base, moved = play(qpos, qvel, actions), play(nudged, qvel, actions)
    return np.asarray(jnp.max(jnp.abs(base - moved), axis=-1)).T


def first_above(curve: np.ndarray, level: float) -> int | None:
    """The first agent step (1-based) at which ``curve`` exceeds ``level``, None if it never does."""
    above = np.nonzero(curve > level)[0]
    return int(above[0]) + 1 if above.size else None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="acrobot_divergence.py", description=__doc__.split("\n")[0])
    p.add_argument("--starts", type=int, default=16)
    p.add_argument("--agent-steps", type=int, default=250, help="agent steps per episode (250 x 4 = 1,000)")
    p.add_argument("--action-repeat", type=int, default=4, help="control steps per agent step (the recipe's 4)")
    p.add_argument("--out", default=None, metavar="PREFIX", help="write PREFIX.csv and PREFIX.png")
    args = p.parse_args(argv)
    for name in ("starts", "agent_steps", "action_repeat"):
        if getattr(args, name) < 1:
            sys.stderr.write(f"error: --{name.replace('_', '-')} must be at least 1, not {getattr(args, name)}\n")
            return 2
    gaps = divergence(args.starts, args.agent_steps, args.action_repeat)
    median, largest = np.median(gaps, axis=0), gaps.max(axis=0)
    q25, q75 = np.percentile(gaps, 25, axis=0), np.percentile(gaps, 75, axis=0)
    shown = sorted({s for s in (1, 5, 10, 25, 50, 100, 150, 200, 250) if s <= args.agent_steps} | {args.agent_steps})
    print("| agent step | " + " | ".join(str(s) for s in shown) + " |")
    print("|---|" + "---:|" * len(shown))
    for label, curve in (("median", median), ("largest", largest)):
        print(f"| {label} | " + " | ".join(f"{curve[s - 1]:.2e}" for s in shown) + " |")
    for label, curve in (("median", median), ("largest", largest)):
        for level in (1e-3, 0.1):
            step = first_above(curve, level)
            print(f"{label} above {level:g} from agent step "
                  + (f"{step} ({step * args.action_repeat} control steps)" if step else "never"))
    print(f"starts whose two plays ended identical: {int(np.sum(gaps[:, -1] == 0))} of {args.starts}")
    if args.out:
        from lnnmpc.train import runfolder

        fields = ["agent_step", "median", "q25", "q75", "max"]
        runfolder.write_csv(f"{args.out}.csv", fields, [
            dict(zip(fields, [s + 1] + [f"{c[s]:.6e}" for c in (median, q25, q75, largest)], strict=True))
            for s in range(gaps.shape[1])])
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from lnnmpc.train.png import save_png

        fig, ax = plt.subplots(figsize=(6, 3.5))
        steps = np.arange(1, gaps.shape[1] + 1)
        shown_floor = lambda c: np.maximum(c, 1e-10)  # noqa: E731 (zero: the plays agree bit for bit)
        ax.fill_between(steps, shown_floor(q25), shown_floor(q75), alpha=0.3, label="25-75th percentile")
        ax.plot(steps, shown_floor(median), label=f"median over {args.starts} starts")
        ax.plot(steps, shown_floor(largest), linestyle="--", label="largest")
        ax.set_yscale("log")
        ax.set_xlabel(f"agent step (x {args.action_repeat} control steps)")
        ax.set_ylabel("largest |observation difference|")
        ax.set_title("acrobot-swingup, uniform random actions: one float32 ulp in the first joint angle", fontsize=9)
        ax.legend(fontsize=8)
        fig.tight_layout()
        save_png(fig, f"{args.out}.png", dpi=120)
        print(f"wrote {args.out}.csv and {args.out}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
