"""Each run's last training evaluation, run by run, grouped into lines (one configuration over several master
seeds): where a sweep of levers landed, beside the bar it aims at.

    python experiments/scripts/final_returns_figure.py --line LABEL=RUN[,RUN...] [--line ...] \
        [--bar 700] [--reference LABEL=VALUE ...] [--title TEXT] [--run-names A,B,...] --out PREFIX

A RUN is a run folder (its ``eval.csv``, the trainer's: ``env_step``, ``seed``, ``episode``, ``return``); its value
is its last evaluation's mean return over its seeds (each seed's episode mean), as its ``summary.md`` gives it.
Lines are drawn in the order given, each run as a dot (the k-th run of every line in one colour, named by
``--run-names``: master seed k when each line lists its runs by master seed) and the line's mean as a bar, with its
value written in it. ``--bar`` draws the target as a dashed line, ``--reference`` other levels as dotted ones.
Writes ``PREFIX.csv`` (one row per run: line, position, run, env_step, return, and the line's mean) and
``PREFIX.png``, and prints each line's runs and mean.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def parse_references(items: list[str]) -> dict[str, float]:
    references = {}
    for item in items:
        label, sep, value = item.rpartition("=")
        try:
            references[label] = float(value)
        except ValueError:
            raise ValueError(f"--reference takes LABEL=VALUE, got {item!r}") from None
        if not sep or not label:
            raise ValueError(f"--reference takes LABEL=VALUE, got {item!r}")
    return references


def run_name(position: int, names: list[str] | None) -> str:
    """The legend's name of the runs at ``position`` in their lines."""
    return names[position] if names and position < len(names) else f"run {position + 1} of each line"


def final_returns(lines: dict[str, list[str]]) -> list[dict]:
    """One row per run: line, position (0-based within its line), run, env_step, return (its last evaluation's
    mean, as its summary gives it: :func:`lnnmpc.analysis.line_measures.run_finals`), line_mean."""
    from lnnmpc.analysis.line_measures import run_finals

    rows = []
    for label, runs in lines.items():
        values = [run_finals(run) for run in runs]  # (step, last evaluation's mean, the last three's mean)
        mean = float(np.mean([value for _, value, _ in values]))
        rows += [{"line": label, "position": k, "run": run, "env_step": step, "return": value, "line_mean": mean}
                 for k, (run, (step, value, _)) in enumerate(zip(runs, values, strict=True))]
    return rows


def plot(rows: list[dict], bar: float | None, references: dict[str, float], title: str, path: str,
         run_names: list[str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lnnmpc.train.png import save_png

    labels = list(dict.fromkeys(row["line"] for row in rows))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.1 * len(labels) + 2.0), 4.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for x, label in enumerate(labels):
        line = [row for row in rows if row["line"] == label]
        mean = line[0]["line_mean"]
        ax.bar(x, mean, width=0.6, color="0.85", edgecolor="0.5")
        ax.text(x, mean * 0.06, f"{mean:.1f}", ha="center", va="bottom", fontsize=9)
        for row in line:
            offset = 0.12 * (row["position"] - (len(line) - 1) / 2)
            ax.plot(x + offset, row["return"], "o", ms=5, color=colours[row["position"] % len(colours)],
                    label=run_name(row["position"], run_names) if x == 0 else None)
    if bar is not None:
        ax.axhline(bar, ls="--", color="tab:red", lw=1.2, label=f"target {bar:g}")
    for k, (name, value) in enumerate(references.items()):
        ax.axhline(value, ls=":", color=colours[(k + 5) % len(colours)], lw=1.2, label=f"{name} {value:g}")
    ax.set_xticks(range(len(labels)), labels, rotation=25, ha="right", fontsize=8)
    ax.set_ylabel("return, last training evaluation")
    ax.set_ylim(0, max([row["return"] for row in rows] + [bar or 0, *references.values()]) * 1.12)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    save_png(fig, path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--line", action="append", required=True, help="LABEL=RUN[,RUN...], repeatable")
    parser.add_argument("--bar", type=float, default=None, help="the target, a dashed line")
    parser.add_argument("--reference", action="append", default=[], help="LABEL=VALUE, a dotted line, repeatable")
    parser.add_argument("--title", default="")
    parser.add_argument("--run-names", default="",
                        help="comma-separated legend names of the lines' 1st, 2nd, ... runs (e.g. master seeds)")
    parser.add_argument("--out", required=True, help="PREFIX of PREFIX.csv and PREFIX.png")
    args = parser.parse_args(argv)
    try:
        from lnnmpc.analysis.line_measures import parse_lines

        rows = final_returns(parse_lines(args.line))
        references = parse_references(args.reference)
    except ValueError as error:
        print(f"final_returns_figure: {error}", file=sys.stderr)
        return 2
    from lnnmpc.train import runfolder

    runfolder.write_csv(f"{args.out}.csv", list(rows[0]),
                        [{**row, "return": f"{row['return']:.4f}", "line_mean": f"{row['line_mean']:.4f}"}
                         for row in rows])
    plot(rows, args.bar, references, args.title, f"{args.out}.png",
         [name for name in args.run_names.split(",") if name])
    for label in dict.fromkeys(row["line"] for row in rows):
        line = [row for row in rows if row["line"] == label]
        values = " / ".join(f"{row['return']:.1f}" for row in line)
        print(f"{label}: {values}, mean {line[0]['line_mean']:.1f}")
    print(f"wrote {args.out}.csv and {args.out}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
