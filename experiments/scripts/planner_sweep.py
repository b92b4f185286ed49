"""Evaluate trained runs under several MPPI settings (planner-only; the parameters do not change): which planner
the final policies play best with.

    python experiments/scripts/planner_sweep.py RUN [RUN ...] --setting "" --setting "iterations=12" \
        --setting "plan_horizon=5 num_samples=1024" [--episodes 10] [--out sweep.csv]

Each ``--setting`` is a space-separated list of KEY=VALUE planner overrides ("" is the run's own planner). Every
(run, setting) is evaluated with ``lnnmpc.evaluate(..., planner=...)`` on MJX (same episodes and keys for every
setting, so the settings are compared on the same starts); one row per (run, setting) is appended to ``--out``
(mean over seeds and episodes, the seeds' means, seconds) and printed.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

import lnnmpc
from lnnmpc.train import runfolder
from lnnmpc.train.config import parse_overrides


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run folders (with checkpoints or policy.npz)")
    p.add_argument("--setting", action="append", required=True,
                   help='space-separated KEY=VALUE planner overrides; "" for the run\'s own planner (repeatable)')
    p.add_argument("--episodes", type=int, default=10, help="episodes per seed")
    p.add_argument("--out", default="planner-sweep.csv", help="CSV the rows are appended to")
    args = p.parse_args()
    for setting in args.setting:
        planner = parse_overrides(setting.split(), "--setting")
        for run in args.runs:
            start = time.perf_counter()
            result = lnnmpc.evaluate(run, episodes=args.episodes, planner=planner, verbose=False)
            seconds = time.perf_counter() - start
            per_seed = result.returns.mean(axis=1)
            row = {"run": os.path.basename(os.path.normpath(run)), "planner": setting or "trained",
                   "env_step": result.checkpoint, "mean": round(result.mean, 2),
                   "seed_means": " ".join(f"{x:.1f}" for x in per_seed),
                   "worst_episode": round(float(np.min(result.returns)), 1), "seconds": round(seconds, 1)}
            runfolder.append_csv(args.out, [row])
            print(", ".join(f"{k}={v}" for k, v in row.items()), flush=True)


if __name__ == "__main__":
    main()
