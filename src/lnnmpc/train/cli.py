"""``make train``: train an agent on one task for several seeds at once and write a run folder.

    python -m lnnmpc.train.cli --task walker-run --seeds 4 --steps 200000 --obs "noise=0.1,flicker=0.2"

Run folder (``runs/<task>-<agent>-<time>`` unless ``--out``): ``config.json`` (resolved settings),
``train.csv`` (env_step, seed, episode returns and losses per chunk), ``eval.csv`` (env_step, seed, episode,
return), ``curve.png`` and ``checkpoints/`` (the whole training state after every evaluation). Environment steps
count dm_control steps (action repeat included), as SPEC §1.

Resume: run the same command with the same ``--out`` again (``--steps`` may be larger); training continues
exactly from the newest checkpoint, and CSV rows written after it are dropped.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc import envs
from lnnmpc.agents.registry import AGENTS, make_agent
from lnnmpc.replay import replay_capacity_for
from lnnmpc.train.checkpoint import latest_step, restore_checkpoint, save_checkpoint
from lnnmpc.train.loop import LoopConfig, TrainingLoop

OBS_KEYS = {"noise": "obs_noise", "obs_noise": "obs_noise", "flicker": "flicker", "delay": "delay",
            "remove_vel": "remove_vel"}


def parse_obs(text: str) -> dict:
    """"noise=0.1,flicker=0.2,delay=3,remove_vel=1" -> make() options; ValueError names unknown keys."""
    options = {}
    for item in filter(None, (part.strip() for part in (text or "").split(","))):
        key, sep, value = item.partition("=")
        if not sep or key not in OBS_KEYS:
            raise ValueError(f"bad observation option {item!r}; use key=value with keys {', '.join(OBS_KEYS)}")
        name = OBS_KEYS[key]
        options[name] = (value.lower() in ("1", "true", "yes")) if name == "remove_vel" else (
            int(value) if name == "delay" else float(value))
    return options


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", required=True, help=f"one of: {', '.join(envs.TASKS)}")
    p.add_argument("--agent", default="tdmpc2", choices=AGENTS)
    p.add_argument("--seeds", type=int, default=1, help="independent seeds trained together (vmap)")
    p.add_argument("--steps", type=int, default=200_000, help="environment steps per seed")
    p.add_argument("--envs", type=int, default=1, help="environments per seed")
    p.add_argument("--obs", default="", help='training corruptions, e.g. "noise=0.1,flicker=0.2"')
    p.add_argument("--eval-obs", default=None, help="evaluation corruptions (default: same as --obs)")
    p.add_argument("--model-size", type=int, default=5, choices=(1, 5))
    p.add_argument("--seed-steps", type=int, default=5000, help="environment steps of random actions first")
    p.add_argument("--eval-every", type=int, default=10_000, help="environment steps between evaluations")
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--physics", default="fast", choices=envs.PROFILES)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--small", action="store_true", help="tiny networks and planner (CPU smoke runs)")
    p.add_argument("--out", default=None, help="run folder (an existing one with checkpoints is resumed)")
    p.add_argument("--replay-capacity", type=int, default=None, help="slots per environment (default: from --steps)")
    return p


def _check(args) -> None:
    if args.task not in envs.TASKS:
        raise ValueError(f"unknown task {args.task!r}; known: {', '.join(envs.TASKS)}")
    for name in ("seeds", "steps", "envs", "eval_episodes", "batch_size", "eval_every"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.seed_steps < 0:
        raise ValueError(f"--seed-steps must be >= 0, got {args.seed_steps}")


def build(args):
    """(loop, run config dict) from parsed arguments."""
    _check(args)
    obs, eval_obs = parse_obs(args.obs), parse_obs(args.obs if args.eval_obs is None else args.eval_obs)
    env = envs.make(args.task, physics=args.physics, **obs)
    eval_env = envs.make(args.task, physics=args.physics, **eval_obs)
    agent = make_agent(args.agent, env.observation_size, env.action_size, model_size=args.model_size,
                       small=args.small)
    capacity = args.replay_capacity or (
        replay_capacity_for(args.steps, env.action_repeat, args.envs) + 2 * (env.episode_length + 1))
    loop = TrainingLoop(agent, env, eval_env, LoopConfig(num_envs=args.envs, batch_size=args.batch_size,
                                                         replay_capacity=capacity,
                                                         eval_episodes=args.eval_episodes))
    config = {"args": vars(args), "obs": obs, "eval_obs": eval_obs, "agent": dataclasses.asdict(agent.config),
              "loop": dataclasses.asdict(loop.config), "device": jax.devices()[0].device_kind}
    return loop, config


class Progress:
    """One-line live progress on stderr: env steps, steps/s, last evaluation."""

    def __init__(self, total: int):
        self.total, self.start, self.last_eval = total, time.perf_counter(), float("nan")

    def show(self, done: int) -> None:
        elapsed = time.perf_counter() - self.start
        width = 30
        filled = int(width * min(done / self.total, 1.0))
        sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {done:>9,}/{self.total:,} env steps  "
                         f"{done / max(elapsed, 1e-9):8.0f} steps/s  last eval {self.last_eval:7.1f}")
        sys.stderr.flush()


def _truncate_csv(path: str, max_env_step: int) -> None:
    """Drops rows written after a checkpoint (env_step > max_env_step), atomically."""
    if not os.path.exists(path):
        return
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        fields, rows = reader.fieldnames, [r for r in reader if int(r["env_step"]) <= max_env_step]
    tmp = f"{path}.tmp"
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


def _resumable_settings(settings: dict) -> dict:
    """The settings a resumed run must share with its checkpoint (all but --steps and --out)."""
    return {k: v for k, v in settings.items() if k not in ("steps", "out")}


def _append_csv(path: str, rows: list[dict]) -> None:
    if not rows:
        return
    new = not os.path.exists(path)
    with open(path, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        if new:
            writer.writeheader()
        writer.writerows(rows)


def plot_curve(run: str) -> None:
    """Writes curve.png (mean ± std of the evaluation return over seeds and episodes); skipped without matplotlib."""
    try:
        import matplotlib
    except ImportError:
        sys.stderr.write("matplotlib is not installed: skipping curve.png\n")
        return

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(os.path.join(run, "eval.csv")) as f:
        rows = list(csv.DictReader(f))
    steps = sorted({int(r["env_step"]) for r in rows})
    means = [np.mean([float(r["return"]) for r in rows if int(r["env_step"]) == s]) for s in steps]
    stds = [np.std([float(r["return"]) for r in rows if int(r["env_step"]) == s]) for s in steps]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(steps, means)
    ax.fill_between(steps, np.subtract(means, stds), np.add(means, stds), alpha=0.3)
    ax.set(xlabel="environment steps", ylabel="evaluation return", title=os.path.basename(run.rstrip("/")))
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(run, "curve.png"), dpi=110)
    plt.close(fig)


def train(args: argparse.Namespace) -> str:
    """Runs the whole schedule; returns the run folder."""
    loop, config = build(args)
    run = args.out or os.path.join("runs", f"{args.task}-{args.agent}-{time.strftime('%Y%m%d-%H%M%S')}")
    os.makedirs(run, exist_ok=True)
    resume_step = latest_step(run)
    if resume_step is not None:
        with open(os.path.join(run, "config.json")) as f:
            saved = json.load(f)["args"]
        saved_args, current = _resumable_settings(saved), _resumable_settings(vars(args))
        if saved_args != current:
            changed = sorted(k for k in saved_args.keys() | current.keys() if saved_args.get(k) != current.get(k))
            raise ValueError(f"{run} holds a run with other settings ({', '.join(changed)}); use another --out")
    with open(os.path.join(run, "config.json"), "w") as f:
        json.dump(config, f, indent=2, default=str)
    seeds, per_iteration = args.seeds, args.envs * loop.env.action_repeat
    vmapped = lambda fn: jax.jit(jax.vmap(fn, in_axes=(0, None)), static_argnums=1)
    seed_chunk, burst, train_chunk = vmapped(loop.seed_chunk), vmapped(loop.update_burst), vmapped(loop.train_chunk)
    evaluate = jax.jit(jax.vmap(loop.evaluate))
    ts = jax.jit(jax.vmap(loop.init))(jax.random.split(jax.random.key(args.seed), seeds))
    progress, env_steps, next_eval, last_eval = Progress(args.steps), 0, args.eval_every, -1
    eval_key = jax.random.key(args.seed + 10_000)
    seeded = False
    if resume_step is not None:
        ts, host = restore_checkpoint(run, resume_step, ts)
        env_steps, next_eval, last_eval, seeded = host["env_steps"], host["next_eval"], host["last_eval"], True
        eval_key = jax.random.wrap_key_data(jnp.asarray(host["eval_key"], jnp.uint32))
        for name in ("train.csv", "eval.csv"):
            _truncate_csv(os.path.join(run, name), env_steps)
        sys.stderr.write(f"resuming {run} at {env_steps} env steps\n")

    def checkpoint() -> None:
        host = {"env_steps": env_steps, "next_eval": next_eval, "last_eval": last_eval,
                "eval_key": np.asarray(jax.random.key_data(eval_key)).tolist()}
        save_checkpoint(run, env_steps, ts, host)

    def account(out) -> list[dict]:
        """Counts environment steps of a chunk and turns finished episodes into train.csv rows."""
        nonlocal env_steps
        returns = np.asarray(out["episode_return"])  # (seeds, iterations, envs)
        terminal = np.isfinite(returns[0, :, 0])
        rows = []
        for i in range(returns.shape[1]):
            if not terminal[i]:
                env_steps += per_iteration
                continue
            for s in range(seeds):
                row = {"env_step": env_steps, "seed": s, "episode_return": float(np.mean(returns[s, i]))}
                row.update({k: float(np.asarray(v)[s, i]) for k, v in out.items()
                            if k not in ("reward", "episode_return")})
                rows.append(row)
        return rows

    def run_eval() -> None:
        nonlocal eval_key, last_eval
        last_eval = env_steps
        eval_key, key = jax.random.split(eval_key)
        returns = np.asarray(evaluate(ts.agent, jax.random.split(key, seeds)))  # (seeds, episodes)
        _append_csv(os.path.join(run, "eval.csv"), [
            {"env_step": env_steps, "seed": s, "episode": e, "return": float(returns[s, e])}
            for s in range(seeds) for e in range(returns.shape[1])])
        progress.last_eval = float(returns.mean())
        plot_curve(run)

    seed_iterations = math.ceil(args.seed_steps / per_iteration)
    if seed_iterations and not seeded:
        ts, out = seed_chunk(ts, seed_iterations)
        _append_csv(os.path.join(run, "train.csv"), account(out))
        ts, _ = burst(ts, seed_iterations * args.envs)  # one update per agent step of the seed phase
        progress.show(env_steps)
    chunk = max(1, min(args.eval_every // per_iteration, 1000))
    while env_steps < args.steps:
        ts, out = train_chunk(ts, chunk)
        _append_csv(os.path.join(run, "train.csv"), account(out))
        if env_steps >= next_eval:
            run_eval()
            next_eval += args.eval_every
            checkpoint()
        progress.show(env_steps)
    if last_eval != env_steps:
        run_eval()
        checkpoint()
    progress.show(env_steps)
    sys.stderr.write(f"\nrun folder: {run}\n")
    return run


def main(argv=None) -> None:
    args = build_parser().parse_args(argv)
    try:
        train(args)
    except ValueError as error:
        sys.exit(f"error: {error}")


if __name__ == "__main__":
    main()
