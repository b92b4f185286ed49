"""How well a run's critic knows what its acting earns: Q(z_t, a_t) against the discounted return that followed.

    python experiments/scripts/value_calibration.py RUN [--episodes 4] [--hanging SIGMA] [--checkpoint STEP]
        [--actor planner|prior] [--tail 0.05] [--out DIR]

Plays seed 0's policy for ``--episodes`` deterministic episodes (MJX, the evaluation protocol,
:func:`lnnmpc.analysis.rollout.rollout`, key 0; with ``--hanging SIGMA`` on acrobot from starts hanging at rest,
as ``acrobot_hanging_starts.py``) and, at every agent step t, evaluates the critic on the latent the agent
planned from and the action it played: the mean and the minimum over all Q heads. ``--actor prior`` plays the
policy prior alone (its mean action), whose continuation the critic's targets value (TD-MPC2 bootstraps with the
prior's action), so that Q and G then describe the same behaviour. It compares them with the
discounted return that followed, G_t = sum_k gamma^k r_{t+k} (float64; the steps whose discount to the episode's
end is above ``--tail``, 0.05, are left out of the summary, since the time limit cuts their return: at gamma 0.99
that keeps the first 202 of 500 agent steps, and none of 250 at action repeat 4, which is refused). On acrobot the
steps are split by whether the tip is above the shoulder: does the critic value the pumping phase, hanging low, as
what it leads to? Writes ``calibration.csv`` (one row per episode and step) and ``calibration.png`` (Q and G over each
episode) to ``--out`` (default <run>/analysis/<step>/value_calibration/) and prints the summary per phase.
``value_vs_return.py`` makes the same comparison as one row per seed (with the reward head's); this one keeps every
step of seed 0, splits acrobot's by the tip's height, plays hanging starts or the prior alone, and plots.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """G_t = r_t + gamma G_{t+1} along the last axis of ``rewards`` (..., T), 0 after the last step; float64."""
    rewards = np.asarray(rewards, np.float64)
    out = np.empty_like(rewards)
    following = np.zeros(rewards.shape[:-1])
    for t in range(rewards.shape[-1] - 1, -1, -1):
        following = rewards[..., t] + gamma * following
        out[..., t] = following
    return out


def uncut_steps(steps: int, gamma: float, tail: float = 0.05) -> int:
    """How many leading steps t of a ``steps``-long episode have gamma^(steps - t) <= ``tail``: those whose return the
    time limit cuts by at most that share of a constant reward's."""
    return max(0, steps - math.ceil(math.log(tail) / math.log(gamma)) + 1)


def phase_summary(q: np.ndarray, g: np.ndarray, keep: np.ndarray) -> dict[str, float]:
    """Mean Q, mean G, mean Q - G and their correlation over the ``keep`` entries of equally shaped arrays."""
    q, g = np.asarray(q, np.float64)[keep], np.asarray(g, np.float64)[keep]
    if q.size == 0:
        return {"steps": 0, "q": float("nan"), "g": float("nan"), "bias": float("nan"), "corr": float("nan")}
    corr = float(np.corrcoef(q, g)[0, 1]) if q.size > 1 and q.std() > 0 and g.std() > 0 else float("nan")
    return {"steps": int(q.size), "q": float(q.mean()), "g": float(g.mean()), "bias": float((q - g).mean()),
            "corr": corr}


def _hanging_init(sigma: float):
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "acrobot_hanging_starts.py")
    spec = importlib.util.spec_from_file_location("acrobot_hanging_starts", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.hanging_init(sigma)


def critic_values(agent, state, latents: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean and the minimum over every Q head of Q(z, a) for latents (..., Z) and actions (..., A)."""
    heads = jnp.arange(agent.config.model.num_q)
    flat_z = jnp.asarray(latents).reshape(-1, latents.shape[-1])
    flat_a = jnp.asarray(actions).reshape(-1, actions.shape[-1])
    q = jax.jit(lambda z, a: agent._q_values(state.params, z, a, heads))(flat_z, flat_a)  # (heads, N)
    shape = latents.shape[:-1]
    return np.asarray(q.mean(axis=0)).reshape(shape), np.asarray(q.min(axis=0)).reshape(shape)


def plot(path: str, q: np.ndarray, g: np.ndarray, above: np.ndarray | None, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lnnmpc.train.png import save_png

    episodes = q.shape[0]
    fig, axes = plt.subplots(episodes, 1, figsize=(9, 2.2 * episodes), sharex=True, squeeze=False)
    for e, ax in enumerate(axes[:, 0]):
        ax.plot(g[e], label="discounted return that followed, G_t", color="black")
        ax.plot(q[e], label="Q(z_t, a_t), mean of the heads", color="tab:blue")
        if above is not None:
            ax.fill_between(np.arange(q.shape[1]), 0, 1, where=above[e], transform=ax.get_xaxis_transform(),
                            color="tab:green", alpha=0.12, label="tip above the shoulder")
        ax.set_ylabel(f"episode {e}")
    axes[0, 0].legend(loc="upper left", fontsize=7)
    axes[-1, 0].set_xlabel("agent step")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_png(fig, path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--hanging", type=float, default=None, metavar="SIGMA")
    p.add_argument("--checkpoint", type=int, default=None)
    p.add_argument("--actor", default="planner", choices=("planner", "prior"))
    p.add_argument("--tail", type=float, default=0.05,
                   help="leave out the steps whose discount to the episode's end is above this (0 < TAIL < 1)")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if not 0 < args.tail < 1:
        print(f"--tail must lie in (0, 1), got {args.tail}", file=sys.stderr)
        return 2
    from lnnmpc.agents.actor import with_actor
    from lnnmpc.analysis.rollout import rollout
    from lnnmpc.envs.env import Env
    from lnnmpc.train import runfolder
    from lnnmpc.train.evaluate import load_policy

    task = runfolder.saved_config(args.run).task
    if args.episodes < 1 or (args.hanging is not None and (args.hanging < 0 or not task.startswith("acrobot"))):
        print(f"--episodes must be >= 1 and --hanging (>= 0) needs an acrobot run; got {args.episodes}, "
              f"{args.hanging} and {task}", file=sys.stderr)
        return 2
    if args.hanging is not None:
        Env.initial_qpos_qvel = _hanging_init(args.hanging)  # before anything traces a reset
    policy = load_policy(args.run, args.checkpoint)
    agent, state = policy.loop.agent, policy.seed_state(0)
    gamma, steps = float(agent.config.gamma), policy.loop.eval_env.episode_length
    kept = uncut_steps(steps, gamma, args.tail)
    if kept == 0:
        print(f"no step of a {steps}-step episode has a discount to its end of at most --tail {args.tail} at gamma "
              f"{gamma}: the time limit cuts every return; give a --tail above {gamma ** steps:.3g}", file=sys.stderr)
        return 2
    records = rollout(with_actor(agent, args.actor), state, policy.loop.eval_env, jax.random.key(0), args.episodes)
    q_mean, q_min = critic_values(agent, state, records["latent"], records["action"])
    g = discounted_returns(records["reward"], gamma)
    keep = np.zeros_like(g, bool)
    keep[:, :kept] = True
    above = None
    phases = {"all": keep}
    if task.startswith("acrobot"):
        from lnnmpc.analysis.acrobot import tip_positions

        tips, shoulder, _, _ = tip_positions(records["qpos"])
        above = tips[..., 2] > shoulder[2]
        phases = {"tip below the shoulder": keep & ~above, "tip above the shoulder": keep & above, "all": keep}
    out = args.out or os.path.join(args.run, "analysis", str(policy.checkpoint), "value_calibration")
    os.makedirs(out, exist_ok=True)
    rows = [{"episode": e, "step": t, "reward": float(records["reward"][e, t]), "return_to_go": float(g[e, t]),
             "q_mean": float(q_mean[e, t]), "q_min": float(q_min[e, t]), "kept": bool(keep[e, t]),
             **({} if above is None else {"tip_above_shoulder": bool(above[e, t])})}
            for e in range(g.shape[0]) for t in range(steps)]
    runfolder.write_csv(os.path.join(out, "calibration.csv"), list(rows[0]), rows)
    starts = "hanging starts" if args.hanging is not None else "dm_control's initial states"
    print(f"{args.run} (step {policy.checkpoint}, seed 0, {args.actor} acting), {args.episodes} episodes from "
          f"{starts}, gamma {gamma}; "
          f"returns {' '.join(f'{r:.0f}' for r in records['reward'].sum(axis=1))}; the first "
          f"{kept} of {steps} steps kept")
    for name, mask in phases.items():
        s = phase_summary(q_mean, g, mask)
        s_min = phase_summary(q_min, g, mask)
        print(f"  {name}: {s['steps']} steps, Q mean of heads {s['q']:.1f} (min of heads {s_min['q']:.1f}), "
              f"G {s['g']:.1f}, Q - G {s['bias']:+.1f}, correlation {s['corr']:.2f}")
    plot(os.path.join(out, "calibration.png"), q_mean, g, above,
         f"{os.path.basename(os.path.normpath(args.run))}, step {policy.checkpoint}: critic against the return "
         f"that followed ({starts}, {args.actor} acting)")
    print(f"-> {out}/calibration.csv, calibration.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
