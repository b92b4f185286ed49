"""Per-seed statistics of a trained run's deterministic episodes: what :mod:`lnnmpc.analysis.cartpole` and
:mod:`lnnmpc.analysis.acrobot` share (the rollout of each seed, the rows, the figure of each episode over time, the
command line)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from lnnmpc.train import runfolder
from lnnmpc.train.png import save_png

EpisodeStats = Callable[[np.ndarray], dict[str, np.ndarray]]


@dataclasses.dataclass(frozen=True)
class Trace:
    """One quantity of each episode over time, for the figure: ``values`` (E, T); ``band`` (low, high): the region
    the task rewards, shaded (None: none)."""

    label: str
    values: np.ndarray
    band: tuple[float, float] | None = None


EpisodeTraces = Callable[[np.ndarray], list[Trace]]


Column = tuple[str, str, str]  # (header, row key, format spec) of a markdown table
SEED_COLUMNS: tuple[Column, ...] = (("seed", "seed", ""), ("return", "return", ".1f"))


def seeds_progress(episodes: int):
    """The progress line of :func:`seed_rollouts` over a run's seeds (:class:`lnnmpc.train.report.StepProgress`)."""
    from lnnmpc.train.report import StepProgress

    return StepProgress(f"agent steps ({episodes} episode(s) per seed, one seed after another, MJX)")


def seed_rollouts(policy, episodes: int, length: int | None = None,
                  progress: Callable[[int, int], None] | None = None) -> Iterator[tuple[int, Any, dict]]:
    """Yields (seed, agent state, :func:`lnnmpc.analysis.rollout.rollout`'s records) for each trained seed of a
    loaded ``policy`` (:func:`lnnmpc.train.evaluate.load_policy`): ``episodes`` deterministic episodes of ``length``
    agent steps (default the task's), the same key for every seed, one seed after another; ``progress(done,
    total)``: agent steps over all seeds."""
    import jax

    from lnnmpc.analysis.rollout import rollout

    seeds = policy.config.seeds
    for seed in range(seeds):
        state = policy.seed_state(seed)
        report = None if progress is None else (
            lambda done, total, seed=seed: progress(seed * total + done, seeds * total))
        yield seed, state, rollout(policy.loop.agent, state, policy.loop.eval_env, jax.random.key(0), episodes,
                                   length, report)


def rows_of(checkpoint: int, qpos: list[np.ndarray], returns: list[float], episode_stats: EpisodeStats) -> list[dict]:
    """One row per seed: ``env_step``, ``seed``, ``episodes``, the mean ``return`` and the means over the episodes of
    ``episode_stats`` (joint positions (E, T, nq) -> name -> (E,))."""
    return [{"env_step": checkpoint, "seed": seed, "episodes": len(q), "return": ret,
             **{name: float(values.mean()) for name, values in episode_stats(q).items()}}
            for seed, (q, ret) in enumerate(zip(qpos, returns, strict=True))]


def markdown_table(rows: list[dict], columns: Sequence[Column]) -> str:
    """``rows`` as a markdown table of ``columns`` (header, key, format spec), all right-aligned."""
    lines = ["| " + " | ".join(header for header, _, _ in columns) + " |", "|" + "---:|" * len(columns)]
    lines += ["| " + " | ".join(f"{row[key]:{spec}}" for _, key, spec in columns) + " |" for row in rows]
    return "\n".join(lines)


def plot_traces(path: str, traces: list[list[Trace]], title: str) -> None:
    """A figure of each seed's episodes over time: one column per seed, one row per :class:`Trace` (its episodes
    as thin lines, the rewarded band shaded); ``traces[seed]`` the seed's traces."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = len(traces[0]), len(traces)
    fig, axes = plt.subplots(rows, cols, figsize=(max(3.6 * cols, 5.0), 2.4 * rows + 0.4), squeeze=False,
                             sharex=True, sharey="row")
    for seed, seed_traces in enumerate(traces):
        for row, trace in enumerate(seed_traces):
            ax = axes[row, seed]
            if trace.band is not None:
                ax.axhspan(*trace.band, color="tab:green", alpha=0.15, lw=0)
            ax.plot(np.asarray(trace.values).T, lw=0.7, alpha=0.8)
            ax.grid(alpha=0.3)
            if seed == 0:
                ax.set_ylabel(trace.label, fontsize=8)
            if row == 0:
                ax.set_title(f"seed {seed}", fontsize=9)
            if row == rows - 1:
                ax.set_xlabel("agent step", fontsize=8)
    fig.suptitle(title, fontsize=10, wrap=True)
    fig.tight_layout()
    save_png(fig, path, dpi=110)
    plt.close(fig)


def analysis_main(argv: Sequence[str] | None, *, prog: str, description: str, domain: str, filename: str,
                  columns: Sequence[Column], episode_stats: EpisodeStats, episode_traces: EpisodeTraces,
                  shaded: str) -> int:
    """The command line of a per-seed episode analysis: ``RUN [--checkpoint STEP] [--episodes 4] [--length T]
    [--out FOLDER]``; writes ``<out>/<filename>`` (the rows of :func:`rows_of`, ``episode_stats``' keys as the
    ``columns`` name them) and beside it the figure of ``episode_traces`` (the same name, ``.png``, its title naming
    the ``shaded`` bands; default out ``<run>/analysis/<step>``), prints the rows as a markdown table of the seed,
    its return and ``columns``. Returns 0, or 2 (with the reason on stderr) for bad arguments or a run of another
    domain."""
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
    from lnnmpc.train.evaluate import load_policy

    try:
        task = runfolder.saved_config(args.run).task
        if not task.startswith(domain):
            raise ValueError(f"{args.run} trained on {task}: this analysis reads {domain}'s joints")
        policy = load_policy(args.run, args.checkpoint)
    except (ValueError, FileNotFoundError) as error:
        print(error, file=sys.stderr)
        return 2
    qpos, returns = [], []
    for _, _, records in seed_rollouts(policy, args.episodes, args.length, seeds_progress(args.episodes)):
        qpos.append(records["qpos"])
        returns.append(float(records["reward"].sum(axis=1).mean()))
    rows = rows_of(policy.checkpoint, qpos, returns, episode_stats)
    out = args.out or os.path.join(args.run, "analysis", str(policy.checkpoint))
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, filename)
    runfolder.write_csv(path, ["env_step", "seed", "episodes", "return", *(key for _, key, _ in columns)], rows)
    figure = os.path.splitext(path)[0] + ".png"
    plot_traces(figure, [episode_traces(q) for q in qpos],
                f"{task} {policy.config.agent} at {policy.checkpoint:,} env steps\n{args.episodes} deterministic "
                f"episode(s) per seed; shaded: {shaded}")
    print(markdown_table(rows, (*SEED_COLUMNS, *columns)))
    print(f"-> {path}, {figure}")
    return 0
