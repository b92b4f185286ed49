"""Per-seed statistics of a trained run's deterministic episodes: what :mod:`lnnmpc.analysis.cartpole` and
:mod:`lnnmpc.analysis.acrobot` share (the rollout of each seed, the rows, the command line)."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence

import numpy as np

from lnnmpc.train import runfolder

EpisodeStats = Callable[[np.ndarray], dict[str, np.ndarray]]


def seed_rows(run: str, domain: str, episode_stats: EpisodeStats, checkpoint: int | None = None, episodes: int = 4,
              length: int | None = None, progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """One row per trained seed of ``run`` (a run of a ``domain`` task): its episodes' mean return and the means
    over ``episodes`` deterministic episodes of ``length`` agent steps (default the task's) of ``episode_stats``
    (joint positions (E, T, nq) -> name -> (E,)), with ``env_step``. ``progress(done, total)``: agent steps over
    all seeds (played one seed after another). Raises ValueError for a run of another domain."""
    import jax

    from lnnmpc.analysis.rollout import rollout
    from lnnmpc.train.evaluate import load_policy

    config = runfolder.saved_config(run)
    if not config.task.startswith(domain):
        raise ValueError(f"{run} trained on {config.task}: this analysis reads {domain}'s joints")
    policy = load_policy(run, checkpoint)
    rows = []
    for seed in range(config.seeds):
        state = policy.seed_state(seed)
        report = None if progress is None else (
            lambda done, total, seed=seed: progress(seed * total + done, config.seeds * total))
        records = rollout(policy.loop.agent, state, policy.loop.eval_env, jax.random.key(0), episodes, length,
                          report)
        stats = episode_stats(records["qpos"])
        rows.append({"env_step": policy.checkpoint, "seed": seed, "episodes": episodes,
                     "return": float(records["reward"].sum(axis=1).mean()),
                     **{name: float(values.mean()) for name, values in stats.items()}})
    return rows


def analysis_main(argv: Sequence[str] | None, *, prog: str, description: str, domain: str, filename: str,
                  stats: Sequence[str], episode_stats: EpisodeStats, markdown: Callable[[list[dict]], str]) -> int:
    """The command line of a per-seed episode analysis: ``RUN [--checkpoint STEP] [--episodes 4] [--length T]
    [--out FOLDER]``; writes ``<out>/<filename>`` (default out ``<run>/analysis/<step>``), prints ``markdown``.
    Returns 0, or 2 (with the reason on stderr) for bad arguments or a run of another domain."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("run", help=f"run folder of a {domain} task")
    p.add_argument("--checkpoint", type=int, default=None, help="env step of the checkpoint (default: the newest)")
    p.add_argument("--episodes", type=int, default=4, help="deterministic episodes per seed")
    p.add_argument("--length", type=int, default=None, help="agent steps per episode (default: the task's)")
    p.add_argument("--out", default=None, help=f"folder of {filename} (default <run>/analysis/<step>)")
    args = p.parse_args(argv)
    if args.episodes < 1 or (args.length is not None and args.length < 2):
        print(f"--episodes must be >= 1 and --length >= 2, got {args.episodes} and {args.length}", file=sys.stderr)
        return 2
    from lnnmpc.train.report import StepProgress

    progress = StepProgress(f"agent steps ({args.episodes} episode(s) per seed, one seed after another, MJX)")
    try:
        rows = seed_rows(args.run, domain, episode_stats, args.checkpoint, args.episodes, args.length, progress)
    except (ValueError, FileNotFoundError) as error:
        print(error, file=sys.stderr)
        return 2
    out = args.out or os.path.join(args.run, "analysis", str(rows[0]["env_step"]))
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, filename)
    runfolder.write_csv(path, ["env_step", "seed", "episodes", "return", *stats], rows)
    print(markdown(rows))
    print(f"-> {path}")
    return 0
