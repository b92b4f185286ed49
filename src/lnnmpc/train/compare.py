"""``python -m lnnmpc.train.compare RUN [RUN ...] --out FIG.png``: learning curves of several runs on one plot.

    python -m lnnmpc.train.compare runs/a runs/b --labels "raw inputs" "symlog inputs" --out walker.png
    make compare RUNS="runs/a runs/b" OUT=walker.png

Each run folder's ``eval.csv`` becomes one curve: mean over seeds of each seed's episode mean, shaded ± std over
seeds (over episodes for a one-seed run), as in the run's own ``curve.png``. Where all runs share a task and
evaluation corruption, the thesis's final returns for their agents are drawn as horizontal reference lines.
A CSV beside the figure (same name, ``.csv``) holds the plotted numbers: run, label, env_step, mean, std, seeds.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, command_status
from lnnmpc.train.references import references
from lnnmpc.train.report import eval_table


def default_label(config: dict) -> str:
    """``agent`` plus what tells runs apart: corruptions and agent overrides (``cfc-zp-det remove_vel=True``)."""
    c = config["config"]
    parts = [c["agent"]] + [f"{k}={v}" for k, v in c["obs"].items()]
    parts += [f"{k}={v}" for k, v in sorted(c.get("overrides", {}).items())]
    return " ".join(parts)


def load_curves(runs: list[str], labels: list[str] | None = None) -> list[dict]:
    """One entry per run: {"run", "label", "task", "agent", "eval_obs", "table"} (table: :func:`eval_table` rows).

    Raises ConfigError naming a folder that is not a run folder or has no evaluation yet, and a label count
    that does not match the runs."""
    if not runs:
        raise ConfigError("give at least one run folder")
    if labels is not None and len(labels) != len(runs):
        raise ConfigError(f"{len(labels)} label(s) for {len(runs)} run(s); give one label per run or none")
    curves = []
    for i, run in enumerate(runs):
        config = runfolder.read_config(run)
        table = eval_table(runfolder.read_csv(os.path.join(run, "eval.csv")))
        if not table:
            raise ConfigError(f"{run!r} has no evaluation rows in eval.csv yet")
        c = config["config"]
        curves.append({"run": run, "label": labels[i] if labels else default_label(config), "task": c["task"],
                       "agent": c["agent"], "eval_obs": c["eval_obs"], "table": table})
    return curves


def shared_references(curves: list[dict]) -> dict[str, float]:
    """The thesis's reference returns of every plotted agent, when all runs share task and evaluation corruption."""
    if len({(c["task"], str(sorted(c["eval_obs"].items()))) for c in curves}) != 1:
        return {}
    refs = {}
    for c in curves:
        refs.update(references(c["task"], c["agent"], c["eval_obs"]))
    return refs


def reference_lines(curves: list[dict]) -> list[tuple[str, float, object]]:
    """(label, return, matplotlib line style) of every shared reference; styles repeat past four references."""
    styles = ("--", ":", "-.", (0, (1, 3)))
    return [(label, value, styles[i % len(styles)])
            for i, (label, value) in enumerate(shared_references(curves).items())]


def write_comparison(curves: list[dict], out: str, title: str | None = None) -> tuple[str, str]:
    """Writes the figure ``out`` and its numbers ``<out without extension>.csv``; returns both paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    lines = reference_lines(curves)
    outside = len(curves) + len(lines) > 6  # a long legend goes beside the axes instead of over the curves
    fig, ax = plt.subplots(figsize=(9.5 if outside else 7, 4.2))
    rows = []
    for curve in curves:
        steps = [t["env_step"] for t in curve["table"]]
        mean = np.asarray([t["mean"] for t in curve["table"]])
        std = np.asarray([t["std"] for t in curve["table"]])
        seeds = curve["table"][-1]["seeds"]
        line, = ax.plot(steps, mean, marker="o", markersize=3,
                        label=f"{curve['label']} ({seeds} seed{'s' if seeds != 1 else ''})")
        ax.fill_between(steps, mean - std, mean + std, alpha=0.2, color=line.get_color())
        rows += [{"run": curve["run"], "label": curve["label"], "env_step": t["env_step"], "mean": t["mean"],
                  "std": t["std"], "seeds": t["seeds"]} for t in curve["table"]]
    for label, value, style in lines:
        ax.axhline(value, linestyle=style, color="gray", linewidth=1, label=f"{label}: {value:.0f}")
    tasks = sorted({c["task"] for c in curves})
    one_seed = any(c["table"][-1]["seeds"] == 1 for c in curves)
    spread = "seeds;\nover episodes for a one-seed run" if one_seed else "seeds"
    ax.set(xlabel="environment steps", ylabel=f"evaluation return (mean ± std over {spread})",
           title=title or ", ".join(tasks), ylim=(0, 1000))
    ax.grid(alpha=0.3)
    if outside:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    else:
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    table_path = os.path.splitext(out)[0] + ".csv"
    runfolder.write_csv(table_path, list(rows[0]), rows)
    return out, table_path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lnnmpc.train.compare", description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", help="run folders")
    p.add_argument("--labels", nargs="+", default=None, help="one legend label per run (default: agent, "
                   "corruptions and overrides)")
    p.add_argument("--out", required=True, help="figure path (.png); the numbers go to the same name .csv")
    p.add_argument("--title", default=None)
    args = p.parse_args(argv)

    def compare() -> str:
        figure, table = write_comparison(load_curves(args.runs, args.labels), args.out, args.title)
        return f"wrote {figure} and {table}"

    return command_status(compare)


if __name__ == "__main__":
    sys.exit(main())
