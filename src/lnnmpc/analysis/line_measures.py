"""``python -m lnnmpc.analysis.line_measures``: each line's final measures, run by run, with the line's mean.

    python -m lnnmpc.analysis.line_measures --line LABEL=RUN[,RUN...] [--line ...] \\
        [--csv LABEL:MEASURE=CSV[,CSV...] ...] [--pool LABEL=LINE+LINE[+...] ...] [--out TABLE.md]

A line is one configuration trained once per master seed (one RUN folder each, in master-seed order), and a lever is
judged by its line's final policies on several measures at once: the trainer's last evaluation, the mean of its
last three, and evaluations of the final policies played apart (``cli eval`` CSVs: the shared MJX episodes, dm_control,
...). Adding these up by hand, over three runs and then over two launches of one command, is where slips get in;
this prints them from the files.

One markdown row per line: the trainer's last evaluation (each run's mean over its seeds, as its ``summary.md``
gives it; the runs of a line must have evaluated at one step) and the mean of its last three evaluations, then each
MEASURE that a ``--csv`` gave the line (one CSV per run, in the line's run order; a CSV's value is its mean return
over its seeds' episode means, as ``cli eval`` prints it), each cell "run / run / run: mean". ``--pool LABEL=A+B``
adds a row averaging the means of lines A and B (two launches of one command read together) in each column all of
them have; other cells stay empty. ``--out`` also writes the table to a file.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, command_status
from lnnmpc.train.paired import read_episode_returns
from lnnmpc.train.report import eval_table

TRAINER, LAST_THREE = "trainer's last evaluation", "mean of the last 3 evaluations"


def _label_and_list(item: str, option: str, form: str, separator: str) -> tuple[str, list[str]]:
    label, sep, rest = item.partition("=")
    parts = rest.split(separator) if rest else []
    if not sep or not label.strip() or not parts or not all(p.strip() for p in parts):
        raise ConfigError(f"{option} takes {form}, got {item!r}")
    return label.strip(), [p.strip() for p in parts]


def parse_lines(items: list[str]) -> dict[str, list[str]]:
    """``LABEL=RUN[,RUN...]`` items -> {label: runs}, in order; ConfigError naming a malformed or repeated one."""
    lines: dict[str, list[str]] = {}
    for item in items:
        label, runs = _label_and_list(item, "--line", "LABEL=RUN[,RUN...]", ",")
        if label in lines:
            raise ConfigError(f"--line {label!r} given twice")
        lines[label] = runs
    return lines


def parse_csvs(items: list[str], lines: dict[str, list[str]]) -> dict[str, dict[str, list[str]]]:
    """``LABEL:MEASURE=CSV[,CSV...]`` items -> {measure: {line label: csvs}}, measures in order of first mention;
    ConfigError for an unknown line (naming the known ones), a measure given twice for a line, or a CSV count
    other than the line's run count."""
    measures: dict[str, dict[str, list[str]]] = {}
    for item in items:
        key, csvs = _label_and_list(item, "--csv", "LABEL:MEASURE=CSV[,CSV...]", ",")
        label, colon, measure = key.rpartition(":")
        label, measure = label.strip(), measure.strip()
        if not colon or not label or not measure:
            raise ConfigError(f"--csv takes LABEL:MEASURE=CSV[,CSV...], got {item!r}")
        if label not in lines:
            raise ConfigError(f"--csv {item!r}: no --line {label!r}; the lines: {', '.join(lines)}")
        if label in measures.get(measure, {}):
            raise ConfigError(f"--csv gives measure {measure!r} of line {label!r} twice")
        if len(csvs) != len(lines[label]):
            raise ConfigError(f"--csv {label}:{measure} names {len(csvs)} CSV(s) for the line's "
                              f"{len(lines[label])} run(s), one per run in the line's order")
        measures.setdefault(measure, {})[label] = csvs
    return measures


def parse_pools(items: list[str], lines: dict[str, list[str]]) -> dict[str, list[str]]:
    """``LABEL=LINE+LINE[+...]`` items -> {label: line labels}; ConfigError for an unknown line or a label that is
    already a line's or another pool's."""
    pools: dict[str, list[str]] = {}
    for item in items:
        label, members = _label_and_list(item, "--pool", "LABEL=LINE+LINE[+...]", "+")
        if label in lines or label in pools:
            raise ConfigError(f"--pool label {label!r} is already taken by a line or a pool")
        unknown = [m for m in members if m not in lines]
        if unknown:
            raise ConfigError(f"--pool {label!r}: no --line {', '.join(map(repr, unknown))}; "
                              f"the lines: {', '.join(lines)}")
        pools[label] = members
    return pools


def run_finals(run: str) -> tuple[int, float, float]:
    """(step, mean return, mean of the last three evaluations' means) of ``run``'s training evaluations;
    ConfigError naming a run without ``eval.csv`` or evaluations."""
    path = os.path.join(run, "eval.csv")
    if not os.path.isfile(path):
        raise ConfigError(f"{run!r} has no eval.csv")
    table = eval_table(runfolder.read_csv(path))
    if not table:
        raise ConfigError(f"{run}/eval.csv holds no evaluation")
    return table[-1]["env_step"], table[-1]["mean"], float(np.mean([t["mean"] for t in table[-3:]]))


def csv_mean(path: str) -> float:
    """A ``cli eval`` CSV's mean return: the mean over its seeds of each seed's episode mean."""
    returns = read_episode_returns(path).returns
    seeds = sorted({seed for seed, _ in returns})
    return float(np.mean([np.mean([r for (s, _), r in returns.items() if s == seed]) for seed in seeds]))


def line_values(lines: dict[str, list[str]], measures: dict[str, dict[str, list[str]]]) -> dict[str, dict]:
    """{line: {column: per-run values}} for the trainer's two columns and each measure the line has; ConfigError
    where a line's runs last evaluated at different steps."""
    values: dict[str, dict] = {}
    for label, runs in lines.items():
        finals = [run_finals(run) for run in runs]
        steps = sorted({step for step, _, _ in finals})
        if len(steps) > 1:
            at = ", ".join(f"{run} {step:,}" for run, (step, _, _) in zip(runs, finals, strict=True))
            raise ConfigError(f"line {label!r}: its runs last evaluated at different steps ({at})")
        values[label] = {TRAINER: [f[1] for f in finals], LAST_THREE: [f[2] for f in finals]}
        for measure, by_line in measures.items():
            if label in by_line:
                values[label][measure] = [csv_mean(path) for path in by_line[label]]
    return values


def _cell(values: list[float] | None) -> str:
    if not values:
        return ""
    return f"{' / '.join(f'{v:.1f}' for v in values)}: **{np.mean(values):.1f}**"


def measures_table(values: dict[str, dict], pools: dict[str, list[str]], measures: list[str]) -> str:
    """The markdown table: one row per line, then one per pool (the mean of its lines' means where all have it)."""
    columns = [TRAINER, LAST_THREE, *measures]
    lines = ["| line | " + " | ".join(columns) + " |", "|---|" + "---:|" * len(columns)]
    for label, by_column in values.items():
        lines.append(f"| {label} | " + " | ".join(_cell(by_column.get(c)) for c in columns) + " |")
    for label, members in pools.items():
        cells = []
        for column in columns:
            means = [np.mean(values[m][column]) for m in members if column in values[m]]
            cells.append(f"pooled **{np.mean(means):.1f}**" if len(means) == len(members) else "")
        lines.append(f"| {label} ({' + '.join(members)}) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lnnmpc.analysis.line_measures",
                                     description=__doc__.split("\n\n")[0].strip("`"))
    parser.add_argument("--line", action="append", required=True, metavar="LABEL=RUN[,RUN...]")
    parser.add_argument("--csv", action="append", default=[], metavar="LABEL:MEASURE=CSV[,CSV...]")
    parser.add_argument("--pool", action="append", default=[], metavar="LABEL=LINE+LINE[+...]")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args(argv)

    def tabulate() -> str:
        lines = parse_lines(args.line)
        measures = parse_csvs(args.csv, lines)
        pools = parse_pools(args.pool, lines)
        table = measures_table(line_values(lines, measures), pools, list(measures))
        if args.out:
            runfolder.write_text(args.out, table)
        return table.removesuffix("\n")  # command_status ends it with its newline

    return command_status(tabulate)


if __name__ == "__main__":
    sys.exit(main())
