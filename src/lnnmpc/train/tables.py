"""``python -m lnnmpc.train.tables RUN [RUN ...]``: markdown tables of several runs, to paste into a results page.

    python -m lnnmpc.train.tables runs/a runs/b --labels "H_plan 10" "H_plan 3"
    python -m lnnmpc.train.tables runs/a --speed-only        # or --returns-only, --commands-only
    python -m lnnmpc.train.tables runs/a runs/b --returns-only --falls-below 400   # walker: who fell, and the rest
    python -m lnnmpc.train.tables runs/seed0 runs/seed1 runs/seed2 --pool "3 seeds"  # one-seed runs as one
    python -m lnnmpc.train.tables runs/a0+runs/a1 runs/b0+runs/b1 --labels A B       # two pooled columns
    python -m lnnmpc.train.tables runs/s0+runs/s1 --evals dm_control-clean-200192.csv --falls-below 400
    python -m lnnmpc.train.tables runs/a --returns-only --eval-column prior_return  # the prior alone (--eval-prior)

Returns (from each ``eval.csv``): one row per evaluation step, and per run the mean ± std over all seeds × episodes,
the std over the seeds' means, and the seeds' means (rounded), then the mean of the last 3 evaluations. A run that
has no evaluation at a step another run has gets an empty cell. With ``--falls-below R``, a second table looks at
each run's last evaluation: how many episodes returned under R (a walker that fell; also counted over the last 3
evaluations), the mean of all, of the others, and the best and worst episode. ``--pool LABEL`` adds one column of
all the runs' seeds together (runs of one configuration started with other master seeds, e.g. one seed per call on a
one-GPU machine); runs joined by ``+`` (``runs/a0+runs/a1``) are one pooled column of their own, and the speed and
commands tables list them one by one. ``--evals NAME`` reads each run's ``evals/NAME`` instead of ``eval.csv``: the
CSV an ``eval`` command wrote (``python -m lnnmpc.train.cli eval RUN --episodes 50 --backend dm_control``), so a
final policy's many-episode evaluation gets the same tables, pooled and split at a return as the training's.
Speed (from each ``timing.csv``, wall seconds): the process's start (imports, devices; runs since the trainer logs
it), compilation, training chunks (total, count, environment steps per chunk per seed), the median chunk's
environment steps per second over all seeds and per seed, evaluations (total, count) and everything logged.
Commands: the command line that started each run (``config.json``'s provenance). These are the tables the READMEs
under ``experiments/results/`` quote.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from lnnmpc.train import runfolder
from lnnmpc.train.compare import add_pool_and_column_args, load_curves, pool_curves, run_curves
from lnnmpc.train.config import ConfigError, command_status
from lnnmpc.train.report import LAST_EVALUATIONS, eval_table


def step_returns(rows: list[dict], step: int) -> np.ndarray:
    """The episode returns (n,) that ``eval.csv`` rows logged at environment step ``step``, all seeds."""
    return np.array([float(r["return"]) for r in rows if int(r["env_step"]) == step])


def episode_stats(rows: list[dict]) -> dict[int, dict]:
    """Per evaluation step of ``eval.csv`` rows: {"mean", "std" (over all seeds × episodes), "seed_std" (over the
    seeds' means; None for a one-seed run, which has no spread over seeds), "seed_means" (by seed order, from
    :func:`eval_table`)}."""
    stats = {}
    for entry in eval_table(rows):
        returns = step_returns(rows, entry["env_step"])
        means = list(entry["per_seed"].values())
        stats[entry["env_step"]] = {"mean": float(np.mean(returns)), "std": float(np.std(returns)),
                                    "seed_std": float(np.std(means)) if len(means) > 1 else None,
                                    "seed_means": means}
    return stats


def returns_table(curves: list[dict]) -> str:
    """The markdown table of the runs' evaluations (``curves``: :func:`load_curves`), one row per step any run
    evaluated at."""
    stats = [episode_stats(curve["rows"]) for curve in curves]
    header = ["env steps"] + [f"{curve['label']}: {part}" for curve in curves
                              for part in ("mean ± std", "over seeds", "seeds")]
    lines = ["| " + " | ".join(header) + " |", "|---:" + "|---:|---:|---" * len(curves) + "|"]
    for step in sorted(set().union(*stats)):
        cells = [f"{step:,}"]
        for run_stats in stats:
            s = run_stats.get(step)
            seed_std = "" if not s or s["seed_std"] is None else f"{s['seed_std']:.1f}"
            cells += ([f"{s['mean']:.1f} ± {s['std']:.1f}", seed_std,
                       " / ".join(f"{m:.0f}" for m in s["seed_means"])] if s else ["", "", ""])
        lines.append("| " + " | ".join(cells) + " |")
    last = ["mean of the last 3"]
    for run_stats in stats:
        recent = [run_stats[step]["mean"] for step in sorted(run_stats)[-LAST_EVALUATIONS:]]
        last += [f"{np.mean(recent):.1f}" if len(recent) == LAST_EVALUATIONS else "", "", ""]
    lines.append("| " + " | ".join(last) + " |")
    return "\n".join(lines)


def falls_table(curves: list[dict], threshold: float) -> str:
    """The markdown table of each run's last evaluation split at ``threshold`` (``curves``: :func:`load_curves`):
    episodes, how many returned under it (and how many of the last 3 evaluations' episodes did), the mean of all
    and of the others (empty when all are under), best and worst episode."""
    lines = [f"| run | env steps | episodes | under {threshold:g} | under {threshold:g}, last {LAST_EVALUATIONS} "
             "evaluations | mean | mean of the others | best | worst |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for curve in curves:
        steps = sorted({int(r["env_step"]) for r in curve["rows"]})
        last = [step_returns(curve["rows"], step) for step in steps[-LAST_EVALUATIONS:]]
        returns, recent = last[-1], np.concatenate(last)
        others = returns[returns >= threshold]
        lines.append(f"| {curve['label']} | {steps[-1]:,} | {returns.size} | {returns.size - others.size} | "
                     f"{int((recent < threshold).sum())} of {recent.size} | "
                     f"{returns.mean():.1f} | {f'{others.mean():.1f}' if others.size else ''} | "
                     f"{returns.max():.1f} | {returns.min():.1f} |")
    return "\n".join(lines)


def speed_row(run: str, seeds: int) -> dict:
    """Wall seconds of one run's phases from its ``timing.csv`` (see the module docstring)."""
    path = os.path.join(run, "timing.csv")
    if not os.path.exists(path):
        raise ConfigError(f"{run!r} has no timing.csv (runs before the trainer wrote one cannot give their speed)")
    rows = runfolder.read_csv(path)
    seconds = lambda phase: [float(r["seconds"]) for r in rows if r["phase"] == phase]  # noqa: E731
    chunks = [r for r in rows if r["phase"] == "train_chunk"]
    rate = float(np.median([float(r["env_steps_per_s_all_seeds"]) for r in chunks])) if chunks else float("nan")
    startup, evaluations = seconds("startup"), seconds("evaluate")  # runs before the startup row have none
    return {"startup_s": sum(startup) if startup else None, "compile_s": sum(seconds("compile")),
            "chunks_s": sum(float(r["seconds"]) for r in chunks),
            "chunks": len(chunks),
            "chunk_steps": int(chunks[0]["env_steps_per_seed"]) if chunks else 0, "steps_per_s": rate,
            "steps_per_s_per_seed": rate / seeds, "evaluations_s": sum(evaluations),
            "evaluations": len(evaluations), "all_s": sum(float(r["seconds"]) for r in rows)}


def speed_table(curves: list[dict]) -> str:
    """The markdown table of the runs' speeds (``curves``: :func:`load_curves`; one row per run)."""
    lines = ["| run | startup s | compile s | training chunks s | env steps/s, all seeds (median chunk) | per seed | "
             "evaluations s | all s |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for curve in curves:
        s = speed_row(curve["run"], curve["config"]["config"]["seeds"])
        startup = "" if s["startup_s"] is None else f"{s['startup_s']:.1f}"
        lines.append(f"| {curve['label']} | {startup} | {s['compile_s']:.1f} | {s['chunks_s']:,.1f} ({s['chunks']} × "
                     f"{s['chunk_steps']:,} steps) | {s['steps_per_s']:.0f} | {s['steps_per_s_per_seed']:.0f} | "
                     f"{s['evaluations_s']:.1f} ({s['evaluations']}) | {s['all_s']:,.0f} |")
    return "\n".join(lines)


def commands_block(curves: list[dict]) -> str:
    """A bash block of the command that started each run (``curves``: :func:`load_curves`; config.json's first
    provenance entry), each after a ``# label`` comment; a run older than provenance records says so."""
    lines = ["```bash"]
    for curve in curves:
        starts = curve["config"].get("provenance")
        lines += [f"# {curve['label']}", starts[0]["command"] if starts else f"# ({curve['run']}: no command recorded)"]
    return "\n".join(lines + ["```"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lnnmpc.train.tables", description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", help="run folders")
    p.add_argument("--labels", nargs="+", default=None, help="one label per run (default: agent, corruptions "
                   "and overrides)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--returns-only", action="store_true", help="only the evaluation table")
    which.add_argument("--speed-only", action="store_true", help="only the speed table")
    which.add_argument("--commands-only", action="store_true", help="only the commands that started the runs")
    p.add_argument("--falls-below", type=float, default=None, metavar="R",
                   help="after the evaluation table, each run's last evaluation split at return R: episodes under "
                   "it (falls, on walker), the mean of the others, best and worst")
    p.add_argument("--evals", default=None, metavar="NAME",
                   help="read each run's evals/NAME (written by `cli eval`, e.g. dm_control-clean-200192.csv) "
                   "instead of eval.csv")
    add_pool_and_column_args(p, "column", "tabulate")
    args = p.parse_args(argv)
    if args.falls_below is not None and not np.isfinite(args.falls_below):
        p.error(f"--falls-below needs a finite return, got {args.falls_below}")

    def tables() -> str:
        # (checks folders and labels; each config.json read once)
        curves = load_curves(args.runs, args.labels, args.evals, args.eval_column)
        pooled = [pool_curves(curves, args.pool)] if args.pool is not None else []
        only = args.returns_only or args.speed_only or args.commands_only
        parts = [returns_table(curves + pooled)] if args.returns_only or not only else []
        if parts and args.falls_below is not None:
            parts.append(falls_table(curves + pooled, args.falls_below))
        parts += [speed_table(run_curves(curves))] if args.speed_only or not only else []
        parts += [commands_block(run_curves(curves))] if args.commands_only or not only else []
        return "\n\n".join(parts)

    return command_status(tables)


if __name__ == "__main__":
    sys.exit(main())
