"""``python -m lnnmpc.train.paired CSV CSV [...]``: policies compared episode by episode, on the same episodes.

    python -m lnnmpc.train.cli eval runs/a --episodes 20 --out a.csv      # one --seed (default 0) for all
    python -m lnnmpc.train.cli eval runs/b --episodes 20 --out b.csv
    python -m lnnmpc.train.paired a.csv b.csv --labels "lr decay" "constant lr" --plot paired.png

Where the initial state sets much of an episode's return (acrobot: the four policies of RESULTS.md [73] correlate
at 0.84-0.94 episode by episode), two policies evaluated on episodes of their own differ by the episodes as much
as by the policies. Evaluations written by ``cli eval`` (``lnnmpc.evaluate``) with one ``--seed`` on one backend
play the same episodes: episode e of seed s starts from the same state. Compared row by row, the episodes' share
of the difference cancels.

The table gives each CSV's mean ± std over its episodes, then for each CSV after the first its difference to the
first: the mean of the per-episode differences, their standard error (sample std / sqrt(n)), the episodes on
which it returns more and less, and the correlation of the two CSVs' returns. ``--plot`` draws each CSV's returns
against the first's, episode by episode. CSVs that do not hold the same episodes are refused with the reason:
another backend, corruption or eval seed, other (seed, episode) rows, several checkpoints in one file, or the
training's ``eval.csv`` (each of its evaluations plays episodes of a key of its own). ``--common`` compares the
rows all CSVs hold instead: an evaluation's first k episodes start as those of a longer one with the same seed
(the same initial states and random draws; a batch of another size can round differently, and a chaotic
episode amplifies that, so one policy's two evaluations of an episode may part).

    python -m lnnmpc.train.paired --runs runs/a runs/b [--step 200128]

compares run folders on their training-time evaluations instead (:func:`read_training_evaluations`): a run's k-th
evaluation draws its episodes from its master seed and k alone (``lnnmpc.train.trainer.evaluation_key_chain``), so
runs of one task with the same master seed, seed count, episode count and evaluation corruption, evaluated at the
same step as their k-th evaluation, played the same episodes whatever else their settings (the rate, the Q heads,
the action repeat). The step is ``--step`` or the last one every run evaluated at (``--step all``: one table per
step they share). Runs whose evaluations fall at other steps (another action repeat or environment count:
200,128 against 200,256) are paired by their k-th evaluation instead, ``--evaluation K`` (1 the first, -1 the
last); runs that differ in any of those, or that started with code older than
``lnnmpc.train.provenance.KEYS_SINCE_COMMIT``, are refused naming why.

The standard error counts the episodes only: it says how surely these trained policies differ on these starts, not
how surely their training settings do. Two launches of one command can part by more (RESULTS.md [91]: the acrobot
recipe launched twice on master seed 1, -31.3 ± 13.0 at 200,128 and -80.2 ± 32.0 at 161,088), so a setting is
judged over master seeds or launches, not on one pair of runs; every comparison prints a note saying so.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import numpy as np

from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, command_status
from lnnmpc.train.png import save_png

# Columns that must agree for two CSVs to hold the same episodes (eval_seed: CSVs written since it is recorded)
_SAME_EPISODES = ("backend", "obs", "eval_seed")


@dataclasses.dataclass(frozen=True)
class EpisodeReturns:
    """One ``cli eval`` CSV: ``returns[(seed, episode)]`` and what decides its episodes."""

    path: str
    returns: dict[tuple[int, int], float]
    episodes_from: dict[str, str]  # backend, obs and eval_seed (absent in CSVs written before it was recorded)
    env_step: int  # the evaluated checkpoint's (one per CSV)

    def values(self, keys: list[tuple[int, int]]) -> np.ndarray:
        """The returns of rows ``keys``, in that order (n,)."""
        return np.array([self.returns[k] for k in keys], dtype=np.float64)


def read_episode_returns(path: str) -> EpisodeReturns:
    """Reads an evaluation CSV that ``cli eval`` wrote; ConfigError for a file that is none."""
    if not os.path.isfile(path):
        raise ConfigError(f"no evaluation CSV at {path!r}")
    rows = runfolder.read_csv(path)
    if not rows:
        raise ConfigError(f"{path!r} holds no evaluation rows")
    missing = [c for c in ("env_step", "seed", "episode", "return", "backend", "obs") if c not in rows[0]]
    if missing:
        raise ConfigError(f"{path!r} is not a CSV of `cli eval` (no {', '.join(missing)} column; a training's "
                          "eval.csv plays other episodes at each evaluation): evaluate each policy with "
                          "`python -m lnnmpc.train.cli eval RUN --out CSV`, or compare runs' training "
                          "evaluations with `--runs RUN RUN`")
    steps = sorted({r["env_step"] for r in rows}, key=int)
    if len(steps) > 1:
        raise ConfigError(f"{path!r} holds evaluations of several checkpoints ({', '.join(steps)}): one per CSV")
    returns = {}
    for r in rows:
        key = (int(r["seed"]), int(r["episode"]))
        if key in returns:
            raise ConfigError(f"{path!r} holds seed {key[0]} episode {key[1]} twice")
        returns[key] = float(r["return"])
    episodes_from = {c: rows[0][c] for c in _SAME_EPISODES if c in rows[0]}
    for c, value in episodes_from.items():
        if any(r[c] != value for r in rows):
            raise ConfigError(f"{path!r} mixes several values of {c}")
    return EpisodeReturns(path=path, returns=returns, episodes_from=episodes_from, env_step=int(steps[0]))


def check_same_episodes(first: EpisodeReturns, other: EpisodeReturns, common: bool = False) -> None:
    """Raises ConfigError where ``other`` does not hold ``first``'s episodes (with ``common``, where the two share
    no (seed, episode) row). An eval seed that either CSV does not record is not checked."""
    for c in _SAME_EPISODES:
        a, b = first.episodes_from.get(c), other.episodes_from.get(c)
        if a is not None and b is not None and a != b:
            raise ConfigError(f"{other.path!r} played other episodes than {first.path!r}: {c} {b!r} against "
                              f"{a!r} (evaluate both with the same --backend, --obs and --seed)")
    if common and not set(first.returns) & set(other.returns):
        raise ConfigError(f"{other.path!r} and {first.path!r} share no (seed, episode) row")
    if not common and set(first.returns) != set(other.returns):
        only_first = sorted(set(first.returns) - set(other.returns))
        only_other = sorted(set(other.returns) - set(first.returns))
        raise ConfigError(f"{other.path!r} and {first.path!r} hold other (seed, episode) rows: only in the first "
                          f"{only_first[:4] or 'none'}, only in {os.path.basename(other.path)!r} "
                          f"{only_other[:4] or 'none'} (evaluate both with the same --episodes, or compare the "
                          "rows they share with --common)")


# What decides a run's training-time episodes besides the evaluation's index: config.json's "config" entries, each
# with the name a refusal gives it
_SAME_TRAINING_EPISODES = {"task": "task", "seed": "master seed (--seed)", "seeds": "seed count (--seeds)",
                           "eval_episodes": "evaluation episodes", "eval_obs": "evaluation corruption",
                           "physics": "physics profile"}


def read_training_evaluations(run: str) -> dict[int, EpisodeReturns]:
    """Every training-time evaluation of run folder ``run`` by env step (ascending), each as
    :class:`EpisodeReturns` whose ``episodes_from`` names what decides its episodes: the settings of
    _SAME_TRAINING_EPISODES and the evaluation's index. Reads the folder once. ConfigError for a folder that is no
    run, an eval.csv holding an episode of one evaluation twice, or a run started with code whose evaluations drew
    other starts (:func:`lnnmpc.train.provenance.check_current_starts`)."""
    from lnnmpc.train.provenance import check_current_starts

    config = runfolder.read_config(run)["config"]
    check_current_starts(run)
    by_step: dict[int, dict[tuple[int, int], float]] = {}
    for r in runfolder.read_csv(os.path.join(run, "eval.csv")):
        step, key = int(r["env_step"]), (int(r["seed"]), int(r["episode"]))
        returns = by_step.setdefault(step, {})
        if key in returns:
            raise ConfigError(f"{run!r}: eval.csv holds an episode of the evaluation at {step} twice")
        returns[key] = float(r["return"])
    settings = {c: json.dumps(config.get(c), sort_keys=True) for c in _SAME_TRAINING_EPISODES}
    return {step: EpisodeReturns(path=run, returns=by_step[step], episodes_from={**settings, "evaluation": str(index)},
                                 env_step=step) for index, step in enumerate(sorted(by_step))}


def evaluation_at(run: str, evaluations: dict[int, EpisodeReturns], step: int) -> EpisodeReturns:
    """Run ``run``'s evaluation at ``step`` out of :func:`read_training_evaluations`' ``evaluations`` (ConfigError
    naming the steps it evaluated at where ``step`` is none of them)."""
    if step not in evaluations:
        raise ConfigError(f"{run!r} evaluated at {', '.join(map(str, evaluations)) or 'no step'}, not at {step}")
    return evaluations[step]


def training_evaluations(runs: list[str], step: int | str | None) -> list[list[EpisodeReturns]]:
    """Per compared step, the runs' training-time evaluations there (checked to hold the same episodes): ``step``
    an env step, None for the last that every run evaluated at, or "all" for each of those in turn. ConfigError
    where the runs share no evaluation step."""
    evaluations = [read_training_evaluations(run) for run in runs]
    common = sorted(set.intersection(*(set(e) for e in evaluations)))
    if not common:
        raise ConfigError(f"the runs share no evaluation step: {', '.join(map(repr, runs))} (runs evaluated "
                          "at other steps, e.g. with another action repeat, pair by their k-th evaluation: "
                          "--evaluation K)")
    out = []
    for chosen in common if step == "all" else [common[-1] if step is None else step]:
        at_step = [evaluation_at(run, e, chosen) for run, e in zip(runs, evaluations, strict=True)]
        for other in at_step[1:]:
            check_same_training_episodes(at_step[0], other)
        out.append(at_step)
    return out


def training_evaluations_by_number(runs: list[str], number: int) -> list[EpisodeReturns]:
    """The runs' ``number``-th training-time evaluations (1 the first, 2 the second, ...; -1 the last), at whatever
    env step each one was: the k-th evaluation's episodes depend on k, not on its step, so runs that evaluate at
    other steps (another action repeat or environment count) play the same episodes there. ConfigError for 0, for
    a run with fewer evaluations, or where the picked evaluations played other episodes (e.g. -1 picking the
    fifth of one run and the sixth of another)."""
    if isinstance(number, bool) or not isinstance(number, int) or number == 0:
        raise ConfigError(f"--evaluation counts from 1 (the first) or from -1 (the last), got {number!r}")
    picked = []
    for run in runs:
        evaluations = list(read_training_evaluations(run).values())
        if abs(number) > len(evaluations):
            raise ConfigError(f"{run!r} holds {len(evaluations)} evaluation(s): --evaluation {number} picks none")
        picked.append(evaluations[number - 1 if number > 0 else number])
    for other in picked[1:]:
        check_same_training_episodes(picked[0], other)
    return picked


def _step(text: str) -> int | str:
    if text == "all":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"an env step or 'all', got {text!r}") from None


def check_same_training_episodes(first: EpisodeReturns, other: EpisodeReturns) -> None:
    """Raises ConfigError where run ``other``'s evaluation played other episodes than run ``first``'s."""
    for c, value in first.episodes_from.items():
        if other.episodes_from[c] != value:
            what = _SAME_TRAINING_EPISODES.get(c, "evaluation number (0: the first)")
            raise ConfigError(f"{other.path!r} played other episodes than {first.path!r} at {first.env_step}: "
                              f"{what} {other.episodes_from[c]} against {value}")


def shared_rows(csvs: list[EpisodeReturns]) -> list[tuple[int, int]]:
    """The (seed, episode) rows every CSV holds, sorted."""
    return sorted(set.intersection(*(set(c.returns) for c in csvs)))


def paired_rows(csvs: list[EpisodeReturns], labels: list[str]) -> list[dict]:
    """One row per CSV over the rows all of them hold: label, episodes, mean and std of its returns; for the
    CSVs after the first also the paired difference to the first (diff, se), the episodes it wins and loses,
    and the correlation (corr)."""
    keys = shared_rows(csvs)
    base = csvs[0].values(keys)
    rows = []
    for label, csv in zip(labels, csvs, strict=True):
        x = csv.values(keys)
        row = {"label": label, "episodes": len(keys), "mean": x.mean(), "std": x.std()}
        if csv is not csvs[0]:
            d = x - base
            row.update(diff=d.mean(), se=d.std(ddof=1) / np.sqrt(d.size) if d.size > 1 else np.nan,
                       wins=int((d > 0).sum()), losses=int((d < 0).sum()),
                       corr=np.corrcoef(x, base)[0, 1] if x.std() > 0 and base.std() > 0 else np.nan)
        rows.append(row)
    return rows


LAUNCH_NOTE = ("note: ± counts the episodes' starts only, not the spread between training launches: two launches "
               "of one command can differ by more (RESULTS.md [91])\n")


def paired_table(rows: list[dict]) -> str:
    """Markdown table of :func:`paired_rows`."""
    first = rows[0]["label"]
    lines = [f"| policy | episodes | mean ± std | minus {first} (± standard error) | more / less than {first} | "
             "correlation |", "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        cells = [r["label"], str(r["episodes"]), f"{r['mean']:.1f} ± {r['std']:.1f}"]
        if "diff" in r:
            se = "" if np.isnan(r["se"]) else f" ± {r['se']:.1f}"
            corr = "" if np.isnan(r["corr"]) else f"{r['corr']:.2f}"
            cells += [f"{r['diff']:+.1f}{se}", f"{r['wins']} / {r['losses']}", corr]
        else:
            cells += ["", "", ""]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_paired(csvs: list[EpisodeReturns], labels: list[str], path: str) -> str:
    """Each later CSV's returns against the first's, one point per episode, with the diagonal; writes ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = shared_rows(csvs)
    base = csvs[0].values(keys)
    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    everything = np.concatenate([c.values(keys) for c in csvs])
    low, high = float(everything.min()), float(everything.max())
    pad = 0.05 * (high - low or 1.0)
    ax.plot([low - pad, high + pad], [low - pad, high + pad], color="0.6", linestyle="--", linewidth=1,
            label="equal return")
    for label, csv in zip(labels[1:], csvs[1:], strict=True):
        ax.scatter(base, csv.values(keys), s=18, alpha=0.8, label=label)
    ax.set_xlabel(f"{labels[0]}: return per episode")
    ax.set_ylabel("return on the same episode")
    ax.set_xlim(low - pad, high + pad)
    ax.set_ylim(low - pad, high + pad)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"the same {len(keys)} episodes", fontsize=10)
    fig.tight_layout()
    save_png(fig, path, dpi=120)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lnnmpc.train.paired", description=__doc__.split("\n")[0])
    p.add_argument("csvs", nargs="+", help="CSVs of `cli eval` with the same episodes (with --runs: run folders); "
                   "the first is the reference")
    p.add_argument("--runs", action="store_true", help="compare run folders on their training-time evaluations")
    p.add_argument("--step", type=_step, default=None, help="with --runs: the env step whose evaluation to compare "
                   "(default: the last that every run evaluated at; all: one table per step they share)")
    p.add_argument("--evaluation", type=int, default=None, metavar="K",
                   help="with --runs: pair each run's K-th evaluation (1 the first, -1 the last) whatever its env "
                        "step, for runs that evaluate at other steps (another action repeat or env count)")
    p.add_argument("--labels", nargs="+", default=None, help="one label per CSV (default: the file names)")
    p.add_argument("--plot", default=None, metavar="PNG", help="also draw each CSV's returns against the first's")
    p.add_argument("--common", action="store_true", help="compare the (seed, episode) rows all CSVs hold (e.g. "
                   "10 episodes against 20 of the same seed: the first 10 start alike)")
    args = p.parse_args(argv)

    def compare() -> str:
        if len(args.csvs) < 2:
            raise ConfigError(f"give at least two CSVs to compare, got {len(args.csvs)}")
        labels = args.labels or [os.path.basename(os.path.normpath(c)) for c in args.csvs]
        if len(labels) != len(args.csvs):
            raise ConfigError(f"{len(labels)} labels for {len(args.csvs)} CSVs: give one label per CSV")
        for option, value in (("--step", args.step), ("--evaluation", args.evaluation)):
            if value is not None and not args.runs:
                raise ConfigError(f"{option} picks a training evaluation: give it with --runs")
        if args.step is not None and args.evaluation is not None:
            raise ConfigError("give --step (an env step every run evaluated at) or --evaluation (each run's K-th "
                              "evaluation), not both")
        if args.evaluation is not None:
            sections = [training_evaluations_by_number(args.csvs, args.evaluation)]
        elif args.runs:
            sections = training_evaluations(args.csvs, args.step)
            if args.plot and len(sections) > 1:
                raise ConfigError("--plot draws one evaluation's episodes: give --step STEP, not all")
        else:
            csvs = [read_episode_returns(c) for c in args.csvs]
            for other in csvs[1:]:
                check_same_episodes(csvs[0], other, args.common)
            for csv in csvs:
                if "eval_seed" not in csv.episodes_from:
                    sys.stderr.write(f"note: {csv.path!r} records no eval_seed (written before it was): taken to be "
                                     "the others'\n")
            sections = [csvs]
        tables = []
        for csvs in sections:
            if not shared_rows(csvs):
                raise ConfigError("the CSVs share no (seed, episode) row that all of them hold")
            table = paired_table(paired_rows(csvs, labels))
            if args.evaluation is not None:
                steps = " / ".join(f"{c.env_step:,}" for c in csvs)
                table = f"evaluation {args.evaluation} of each run, at env step {steps}\n\n{table}"
            tables.append(f"env step {csvs[0].env_step:,}\n\n{table}" if args.step == "all" else table)
        sys.stderr.write(LAUNCH_NOTE)
        text = "\n\n".join(tables)
        if args.plot:
            text += f"\n\nwrote {plot_paired(sections[0], labels, args.plot)}"
        return text

    return command_status(compare)


if __name__ == "__main__":
    sys.exit(main())
