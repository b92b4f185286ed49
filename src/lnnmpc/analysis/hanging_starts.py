"""``python -m lnnmpc.analysis.hanging_starts``: acrobot lines' returns from the hardest starts apart from the rest.

    python -m lnnmpc.analysis.hanging_starts STARTS.csv [STARTS.csv ...] [--fraction 0.33] [--out TABLE.md]

Reads the per-episode CSVs that ``python -m lnnmpc.analysis.acrobot_starts ... --out PREFIX`` writes (PREFIX.csv:
run, source, seed, episode, shoulder, elbow, energy, return; one row per episode played) and splits each source's
episodes at the start energy below which lie the lowest ``--fraction`` of that source's distinct starts: the
acrobot hanging near rest, where every policy scores least ([78]). A source is either the trainer's evaluations
("training evaluation <step>") or the ``cli eval`` CSVs of one kind (their file names without the run's tag and
seed: MJX episodes, dm_control, ...); the cut is one energy per kind, over the distinct starts of all its rows (runs
of one master seed, or all runs of a ``cli eval`` kind, share theirs). For a training evaluation the policy prior's
return on the same episode (``eval.csv``'s ``prior_return``, from ``--eval-prior``) is read from the run folder when
it has one.

One markdown row per line (the runs' folder names without ``-seed<N>``, in order of appearance) and source kind:
episodes, the mean return below the cut and above it, and the prior's where known. Rows repeated across CSVs (a
reference line analysed beside two others) count once.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
from collections import defaultdict

import numpy as np

from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, command_status
from lnnmpc.train.report import column_rows

COLUMNS = ("run", "source", "seed", "episode", "energy", "return")
TRAINING = "training evaluation"


def line_name(run: str) -> str:
    """``.../acrobot-recipe-explorefloor02-seed3`` -> ``acrobot-recipe-explorefloor02``."""
    return re.sub(r"-seed\d+$", "", os.path.basename(os.path.normpath(run)))


def source_kind(source: str) -> str:
    """The group a source's cut is taken over: ``training evaluation`` or a CSV's name less its run tag and seed
    (``mjx-20ep-gamma985-seed1-200256.csv`` -> ``mjx-20ep``; ``dm_control-...`` -> ``dm_control``), with what
    follows the step when anything does (``...-200256-pi128.csv`` -> ``mjx-cpu-20ep -pi128``: another setting)."""
    if source.startswith(TRAINING):
        return TRAINING
    name = os.path.basename(source)
    match = re.match(r"(mjx-\d+ep|mjx-cpu-\d+ep|dm_control-gpu|dm_control)-", name)
    if not match:
        return name
    setting = re.search(r"-\d+(-[^.]+)\.csv$", name)
    return match.group(1) + (f" {setting.group(1)}" if setting else "")


def read_starts(paths: list[str]) -> list[dict]:
    """The rows of acrobot_starts CSVs, each with ``energy`` and ``return`` as floats, repeated rows once."""
    rows, seen = [], set()
    for path in paths:
        if not os.path.isfile(path):
            raise ConfigError(f"{path}: no such file (an acrobot_starts --out PREFIX.csv)")
        with open(path, newline="") as handle:
            reader = csv.DictReader(handle)
            missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise ConfigError(f"{path}: lacks the column(s) {', '.join(missing)} of an acrobot_starts CSV "
                                  f"({', '.join(COLUMNS)})")
            for row in reader:
                key = tuple(row[c] for c in ("run", "source", "seed", "episode"))
                if key in seen:
                    continue
                seen.add(key)
                rows.append({**row, "energy": float(row["energy"]), "return": float(row["return"])})
    if not rows:
        raise ConfigError(f"no episodes in {', '.join(paths)}")
    return rows


def energy_cut(energies: list[float], fraction: float) -> float:
    """The energy below which lie the lowest ``fraction`` of the distinct ``energies`` (at least one of them)."""
    distinct = np.unique(np.asarray(energies, dtype=np.float64))
    index = max(1, int(np.floor(len(distinct) * fraction)))
    return float(distinct[index]) if index < len(distinct) else float("inf")


def prior_returns(run: str, step: int) -> dict[tuple[str, str], float] | None:
    """``(seed, episode) -> prior_return`` of ``run``'s evaluation at ``step``; None without an eval.csv that has
    the column (a run trained without ``--eval-prior``, or a folder not on this machine)."""
    rows = runfolder.read_csv(os.path.join(run, "eval.csv"))  # [] without the file
    if not rows or "prior_return" not in rows[0]:
        return None
    return {(r["seed"], r["episode"]): float(r["return"]) for r in column_rows(rows, "prior_return")
            if int(r["env_step"]) == step}


def split_table(rows: list[dict], fraction: float) -> str:
    """Markdown: per line and source kind, the episodes and mean returns below / above the kind's energy cut."""
    if not 0.0 < fraction < 1.0:
        raise ConfigError(f"--fraction {fraction} must lie strictly between 0 and 1")
    row_kinds = [source_kind(row["source"]) for row in rows]
    kinds: dict[str, list[float]] = defaultdict(list)
    for row, kind in zip(rows, row_kinds, strict=True):
        kinds[kind].append(row["energy"])
    cuts = {kind: energy_cut(energies, fraction) for kind, energies in kinds.items()}
    cells: dict[tuple[str, str], dict[str, list[float]]] = {}
    priors: dict[tuple[str, int], dict | None] = {}
    for row, kind in zip(rows, row_kinds, strict=True):
        side = "low" if row["energy"] < cuts[kind] else "high"
        cell = cells.setdefault((line_name(row["run"]), kind), defaultdict(list))
        cell[side].append(row["return"])
        if kind == TRAINING:
            step = int(row["source"].split()[-1])
            key = (row["run"], step)
            if key not in priors:
                priors[key] = prior_returns(row["run"], step)
            prior = priors[key]
            if prior is not None and (row["seed"], row["episode"]) in prior:
                cell[side + " prior"].append(prior[(row["seed"], row["episode"])])
    header = [f"Starts split at the lowest {fraction:.2f} of each source's distinct start energies: "
              + "; ".join(f"{kind} below {cut:.2f} J" for kind, cut in cuts.items()) + ".", "",
              "| line | source | episodes below / above | return below | return above | prior below | prior above |",
              "|---|---|---|---:|---:|---:|---:|"]

    def mean(values: list[float]) -> str:
        return f"{np.mean(values):.1f}" if values else ""

    body = [f"| {line} | {kind} | {len(c['low'])} / {len(c['high'])} | {mean(c['low'])} | {mean(c['high'])} | "
            f"{mean(c['low prior'])} | {mean(c['high prior'])} |" for (line, kind), c in cells.items()]
    return "\n".join(header + body) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lnnmpc.analysis.hanging_starts",
                                     description=__doc__.split("\n\n")[0].strip("`"))
    parser.add_argument("starts", nargs="+", help="acrobot_starts --out PREFIX.csv files")
    parser.add_argument("--fraction", type=float, default=1 / 3,
                        help="share of each source's distinct starts counted as hanging (default 1/3)")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args(argv)

    def tabulate() -> str:
        table = split_table(read_starts(args.starts), args.fraction)
        if args.out:
            runfolder.write_text(args.out, table)
        return table.removesuffix("\n")

    return command_status(tabulate)


if __name__ == "__main__":
    raise SystemExit(main())
