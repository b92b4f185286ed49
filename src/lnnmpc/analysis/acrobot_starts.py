"""``python -m lnnmpc.analysis.acrobot_starts``: acrobot returns corrected for how hard their episodes' starts were.

    python -m lnnmpc.analysis.acrobot_starts RUN [RUN ...] [--with RUN=CSV ...] [--without-training]
        [--step STEP] [--population 100000] [--out PREFIX]

An acrobot-swingup episode starts at rest with both joint angles uniform in [-π, π] (dm_control's initial-state
distribution), and the start's mechanical energy decides much of the return: a policy scores far more from a start
near the top than from one hanging down. Ten or twenty episodes therefore give a mean that moves with the luck of
their starts as much as with the policy. This analysis recomputes the initial joint angles of the episodes a run's
training-time evaluation played (from the trainer's evaluation keys, :func:`trainer_evaluation_key`) and of clean
``cli eval`` CSVs of its policy (``--with``, MJX or dm_control: derived from the CSV's ``eval_seed``; with
``--without-training`` only these are fitted), computes each start's mechanical energy
(:func:`lnnmpc.analysis.acrobot_physics.mechanical_energy`, 0 at the shoulder's height, 19.6 J upright at rest), and
fits each policy's returns on the energy by least squares. The policy's **adjusted** mean is the fitted line at the
mean energy of ``--population`` starts drawn from the environment's own initial-state distribution: the expected
return over that distribution, with its standard error from the fit (:func:`adjusted_mean`). A run's policy is its
final checkpoint's (``--step``: an earlier evaluation's episodes, for runs whose policy at that step the CSVs
evaluated). Where a policy has episodes of both kinds, the table also gives how much more its training evaluation's
episodes returned than the others at equal start energy (:func:`source_gap`): what the energy leaves out of one set
of starts' luck. Runs started (or resumed) with code older than `provenance.KEYS_SINCE_COMMIT`, whose evaluations drew
their starts otherwise, and CSVs without an ``eval_seed`` column are refused
(:func:`lnnmpc.train.provenance.check_current_starts`).

Prints one markdown row per policy and the mean over the policies; with ``--out PREFIX`` it also writes
``PREFIX.csv`` (one row per episode: run, source, seed, episode, start angles, energy, return) and ``PREFIX.png``
(returns against the start's energy, one colour per policy, the fitted lines and the population's mean energy).
Without ``--out`` it writes nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from lnnmpc.train.config import ConfigError

TRAINING = "training evaluation"  # the ``source`` of a run's own evaluation episodes (then its env step)


def trainer_evaluation_key(seed: int, index: int):
    """The key of a run's ``index``-th training-time evaluation (0: the first), drawn as the trainer draws it
    (:func:`lnnmpc.train.trainer.evaluation_key_chain`, then :func:`~lnnmpc.train.trainer.next_evaluation_key`
    once per evaluation): split into the run's seeds, it gives each seed's episodes."""
    from lnnmpc.train.trainer import evaluation_key_chain, next_evaluation_key

    chain = evaluation_key_chain(seed)
    for _ in range(index + 1):
        chain, key = next_evaluation_key(chain)
    return key


def start_qpos(env, key, seeds: int, episodes: int) -> np.ndarray:
    """Initial joint positions (seeds, episodes, nq) of the episodes that an evaluation with ``key`` plays on
    ``env`` (the trainer's and ``cli eval``'s on MJX: ``key`` split into ``seeds``, episode i's reset key from
    :func:`lnnmpc.train.loop.evaluation_keys`, its start from :meth:`Env.reset_start`)."""
    import jax

    from lnnmpc.train.loop import evaluation_keys

    def one_seed(seed_key):
        resets, _ = evaluation_keys(seed_key, episodes)
        return jax.vmap(lambda k: env.reset_start(k)[0])(resets)

    return np.asarray(jax.vmap(one_seed)(jax.random.split(key, seeds)), np.float64)


def rest_energy(env, qpos: np.ndarray) -> np.ndarray:
    """Mechanical energy (J) of the acrobot at rest at joint positions ``qpos`` (..., 2), float64."""
    import jax

    from lnnmpc.analysis.acrobot_physics import mechanical_energy, params_from_model

    with jax.enable_x64(True):
        q = np.asarray(qpos, np.float64)
        return np.asarray(mechanical_energy(params_from_model(env.mj_model), q, np.zeros_like(q)), np.float64)


def population_energy(env, count: int, seed: int = 0) -> np.ndarray:
    """Rest energies (count,) of ``count`` starts drawn from ``env``'s initial-state distribution."""
    import jax

    keys = jax.random.split(jax.random.key(seed), count)
    qpos = jax.vmap(lambda k: env.initial_qpos_qvel(k)[0])(keys)
    return rest_energy(env, np.asarray(qpos))


@dataclasses.dataclass(frozen=True)
class Adjusted:
    """A policy's returns fitted on the start's energy: ``return ≈ mean + slope (energy - energy_mean)``."""

    episodes: int
    mean: float  # the plain mean return
    energy_mean: float
    slope: float  # return per J
    r: float  # correlation of return and energy
    adjusted: float  # the fitted line at the population's mean energy
    stderr: float  # its standard error (residual variance with n - 2 degrees of freedom)


def adjusted_mean(energy: np.ndarray, returns: np.ndarray, population_mean: float) -> Adjusted:
    """Least-squares line of ``returns`` (n,) on ``energy`` (n,) evaluated at ``population_mean``; its standard
    error s·sqrt(1/n + (population_mean - mean energy)² / Sxx), s² = RSS / (n - 2). Needs n >= 3 and energies
    that differ (ValueError otherwise)."""
    x, y = np.asarray(energy, np.float64), np.asarray(returns, np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"energy and returns must be equal 1-d arrays, got shapes {x.shape} and {y.shape}")
    n = x.size
    if n < 3:
        raise ValueError(f"a line with a standard error needs at least 3 episodes, got {n}")
    dx, dy = x - x.mean(), y - y.mean()
    sxx, syy = float(dx @ dx), float(dy @ dy)
    if sxx == 0:
        raise ValueError("every episode starts at the same energy: no line to fit")
    slope = float(dx @ dy) / sxx
    residual = dy - slope * dx
    s2 = float(residual @ residual) / (n - 2)
    gap = population_mean - x.mean()
    r = float(dx @ dy) / np.sqrt(sxx * syy) if syy > 0 else 0.0
    return Adjusted(episodes=n, mean=float(y.mean()), energy_mean=float(x.mean()), slope=slope, r=r,
                    adjusted=float(y.mean() + slope * gap), stderr=float(np.sqrt(s2 * (1 / n + gap ** 2 / sxx))))


def source_gap(energy: np.ndarray, returns: np.ndarray, trained: np.ndarray) -> float:
    """How much more the episodes marked ``trained`` (bool (n,)) return than the others at equal start energy: the
    difference of the two intercepts of a least-squares fit with one slope for both (nan where either group is
    empty)."""
    trained = np.asarray(trained, bool)
    if trained.all() or not trained.any():
        return float("nan")
    design = np.stack([trained, ~trained, np.asarray(energy, np.float64)], axis=1).astype(np.float64)
    coef, *_ = np.linalg.lstsq(design, np.asarray(returns, np.float64), rcond=None)
    return float(coef[0] - coef[1])


def trainer_episodes(run: str, config, env, step: int | None) -> tuple[int, list[dict]]:
    """(env step, episode rows) of the training-time evaluation at ``step`` (None: its last) of ``run`` (saved
    configuration ``config``): every seed's episodes, each row with its seed and the start's angles (each seed's
    policy is fitted apart)."""
    from lnnmpc.train.paired import evaluation_at, read_training_evaluations

    evaluations = read_training_evaluations(run)
    if not evaluations:
        raise ConfigError(f"{run!r}: eval.csv holds no evaluation")
    chosen = evaluation_at(run, evaluations, max(evaluations) if step is None else step)
    qpos = start_qpos(env, trainer_evaluation_key(config.seed, int(chosen.episodes_from["evaluation"])), config.seeds,
                      config.eval_episodes)
    return chosen.env_step, [{"run": run, "source": f"{TRAINING} {chosen.env_step}", "seed": seed, "episode": episode,
                              "qpos": qpos[seed, episode], "return": value}
                             for (seed, episode), value in chosen.returns.items()]


def dm_control_start_qpos(env, seed: int, episodes: int) -> np.ndarray:
    """Initial joint positions (episodes, nq) of the episodes ``cli eval --backend dm_control --seed seed`` plays
    (the same for every seed of the policy: :func:`lnnmpc.train.dm_backend.episode_tasks`, reset)."""
    from lnnmpc.train.dm_backend import episode_tasks

    starts = []
    for sim in episode_tasks(env, seed, episodes):
        sim.reset()
        starts.append(np.array(sim.physics.data.qpos, np.float64))
    return np.stack(starts)


def csv_episodes(run: str, path: str, config, env, step: int) -> list[dict]:
    """Episode rows of a clean ``cli eval`` CSV of ``run``'s policy at ``step`` (MJX or dm_control; its
    ``eval_seed`` decides the starts); ``config``: the run's saved configuration."""
    import jax

    from lnnmpc.train.paired import read_episode_returns

    evaluation = read_episode_returns(path)
    backend = evaluation.episodes_from.get("backend")
    if backend not in ("mjx", "dm_control") or evaluation.episodes_from.get("obs") != "clean":
        raise ConfigError(f"{path!r}: only clean evaluations are supported (backend mjx or dm_control, obs clean), "
                          f"got backend {backend!r}, obs {evaluation.episodes_from.get('obs')!r}")
    if "eval_seed" not in evaluation.episodes_from:
        raise ConfigError(f"{path!r} records no eval_seed (written before `cli eval` recorded it, 2026-12-04): "
                          "its starts cannot be recomputed")
    if evaluation.env_step != step:
        raise ConfigError(f"{path!r} evaluated the policy at {evaluation.env_step}, the run's evaluation is at {step}")
    seeds, episodes = config.seeds, 1 + max(e for _, e in evaluation.returns)
    seed = int(evaluation.episodes_from["eval_seed"])
    if backend == "mjx":
        qpos = start_qpos(env, jax.random.key(seed), seeds, episodes)
    else:
        qpos = np.broadcast_to(dm_control_start_qpos(env, seed, episodes), (seeds, episodes, env.mj_model.nq))
    return [{"run": run, "source": os.path.basename(path), "seed": s, "episode": e, "qpos": qpos[s, e],
             "return": value} for (s, e), value in sorted(evaluation.returns.items())]


class PolicyFit(NamedTuple):
    """One policy's line (:func:`adjusted_mean`) and what the table and the figure show beside it."""

    label: str
    fit: Adjusted
    trained_mean: float  # the plain mean of its training evaluation's episodes (nan: none fitted)
    gap: float  # :func:`source_gap` of those episodes against the others (nan: not both kinds)
    episodes: list[dict]  # its rows
    trained: np.ndarray  # (episodes,) bool: which rows are its training evaluation's


def policy_fits(rows: list[dict], population_mean: float) -> list[PolicyFit]:
    """One :class:`PolicyFit` per policy ((run, seed) of ``rows``, in their order)."""
    policies: dict[tuple[str, int], list[dict]] = {}
    for row in rows:
        policies.setdefault((row["run"], row["seed"]), []).append(row)
    seeds_of: dict[str, list[int]] = {}
    for run, seed in policies:
        seeds_of.setdefault(run, []).append(seed)
    base = {run: os.path.basename(os.path.normpath(run)) for run in seeds_of}
    # runs of one folder name (study runs of two agents) keep their parent's name too
    names = {run: os.path.join(*os.path.normpath(run).split(os.sep)[-2:])
             if list(base.values()).count(name) > 1 else name for run, name in base.items()}
    out = []
    for (run, seed), group in policies.items():
        label = names[run] + (f" seed {seed}" if len(seeds_of[run]) > 1 else "")
        energy, returns = np.array([r["energy"] for r in group]), np.array([r["return"] for r in group])
        trained = np.array([r["source"].startswith(TRAINING) for r in group])
        out.append(PolicyFit(label, adjusted_mean(energy, returns, population_mean),
                             float(returns[trained].mean()) if trained.any() else float("nan"),
                             source_gap(energy, returns, trained), group, trained))
    return out


def markdown(fits: list[PolicyFit], population: np.ndarray) -> str:
    """The printed table under a line on the ``population``'s energies: one row per policy, then the mean over the
    policies (the adjusted mean's standard error: the root of the summed variances over the count)."""
    lines = [f"population mean start energy {population.mean():.2f} J (sd {population.std():.2f} J over "
             f"{population.size} starts)", "",
             "| policy | episodes | training evaluation | all episodes | start energy (J) | return per J | r | "
             "training evaluation - others at equal energy | adjusted ± s.e. |", "|" + "---|" * 9]
    def cell(value: float) -> str:  # "-" where a policy has no such episodes
        return "-" if np.isnan(value) else f"{value:.1f}"

    for label, fit, trained, gap, *_ in fits:
        lines.append(f"| {label} | {fit.episodes} | {cell(trained)} | {fit.mean:.1f} | {fit.energy_mean:.2f} | "
                     f"{fit.slope:.1f} | {fit.r:.2f} | {cell(gap)} | {fit.adjusted:.1f} ± {fit.stderr:.1f} |")
    if len(fits) > 1:
        k = len(fits)
        every = [f.fit for f in fits]
        se = np.sqrt(sum(f.stderr ** 2 for f in every)) / k
        trained = cell(np.mean([f.trained_mean for f in fits]))
        lines.append(f"| mean of {k} | {sum(f.episodes for f in every)} | {trained} | "
                     f"{np.mean([f.mean for f in every]):.1f} | {np.mean([f.energy_mean for f in every]):.2f} "
                     f"| | | {cell(np.mean([f.gap for f in fits]))} | {np.mean([f.adjusted for f in every]):.1f} ± "
                     f"{se:.1f} |")
    return "\n".join(lines) + "\n"


def plot(path: str, fits: list[PolicyFit], population_mean: float) -> None:
    """Returns against the start's energy per policy (training evaluations as dots, ``--with`` CSVs as crosses),
    each policy's fitted line, the population's mean energy as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lnnmpc.train.png import save_png

    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    for i, policy in enumerate(fits):
        colour, fit = f"C{i % 10}", policy.fit
        energy = np.array([r["energy"] for r in policy.episodes])
        returns = np.array([r["return"] for r in policy.episodes])
        for trained, marker in ((True, "o"), (False, "x")):
            part = policy.trained == trained
            if part.any():
                ax.scatter(energy[part], returns[part], s=14, marker=marker, color=colour, alpha=0.7)
        xs = np.array([energy.min(), energy.max()])
        ax.plot(xs, fit.mean + fit.slope * (xs - fit.energy_mean), color=colour,
                label=f"{policy.label}: {fit.adjusted:.0f} ± {fit.stderr:.0f}")
    ax.axvline(population_mean, color="0.4", linestyle="--", linewidth=1, label="population mean energy")
    ax.set_xlabel("start's mechanical energy at rest (J)")
    ax.set_ylabel("episode return")
    ax.set_title(f"{len(fits)} policies: dots training evaluation, crosses other episodes", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_png(fig, path, dpi=110)
    plt.close(fig)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command's options (module docstring)."""
    p = argparse.ArgumentParser(prog="python -m lnnmpc.analysis.acrobot_starts", description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", help="acrobot run folders (config.json and eval.csv)")
    p.add_argument("--with", dest="extra", nargs="+", default=[], metavar="RUN=CSV",
                   help="a clean MJX `cli eval` CSV of one of the runs' policies at the same step")
    p.add_argument("--step", type=int, help="the training evaluation to read (default each run's last)")
    p.add_argument("--without-training", action="store_true",
                   help="fit the --with CSVs' episodes alone (every run needs one), not the training evaluation's")
    p.add_argument("--population", type=int, default=100_000, help="starts drawn for the mean energy (default 1e5)")
    p.add_argument("--out", default=None, help="also write PREFIX.csv and PREFIX.png (default: print only)")
    return p.parse_args(argv)


def run_analysis(args: argparse.Namespace) -> str:
    """Reads, fits, writes (with ``--out``) and returns the printed table (ConfigError for a bad run, CSV or
    option)."""
    from lnnmpc.train import runfolder
    from lnnmpc.train.setup import config_env

    if args.population < 2:
        raise ConfigError(f"--population must be >= 2, got {args.population}")
    extra: dict[str, list[str]] = {}
    for item in args.extra:
        run, sep, path = item.partition("=")
        if not sep or run not in args.runs:
            raise ConfigError(f"--with takes RUN=CSV with RUN one of the runs given, got {item!r}")
        extra.setdefault(run, []).append(path)
    if args.without_training and set(args.runs) - set(extra):
        raise ConfigError(f"--without-training leaves {sorted(set(args.runs) - set(extra))[0]!r} no episodes: give "
                          "it a CSV with --with")
    rows, env = [], None
    for run in args.runs:
        config = runfolder.saved_config(run)
        if not config.task.startswith("acrobot"):
            raise ConfigError(f"{run!r} trained {config.task}; this analysis reads acrobot runs only")
        env = config_env(config, {})
        step, trained = trainer_episodes(run, config, env, args.step)
        rows += [] if args.without_training else trained
        for path in extra.get(run, []):
            rows += csv_episodes(run, path, config, env, step)
    energies = rest_energy(env, np.stack([r["qpos"] for r in rows]))
    for row, energy in zip(rows, energies, strict=True):
        row["energy"] = float(energy)
    population = population_energy(env, args.population)
    population_mean = float(population.mean())
    fits = policy_fits(rows, population_mean)
    if args.out:
        kept = ("run", "source", "seed", "episode", "energy", "return")
        runfolder.write_csv(f"{args.out}.csv", [*kept[:4], "shoulder", "elbow", *kept[4:]],
                            [{**{k: r[k] for k in kept}, "shoulder": float(r["qpos"][0]),
                              "elbow": float(r["qpos"][1])} for r in rows])
        plot(f"{args.out}.png", fits, population_mean)
    return markdown(fits, population)


def main(argv: Sequence[str] | None = None) -> int:
    from lnnmpc.train.config import command_status

    args = parse_args(argv)
    return command_status(lambda: run_analysis(args))


if __name__ == "__main__":
    sys.exit(main())
