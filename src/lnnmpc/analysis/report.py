"""``python -m lnnmpc.analysis.report RUN``: the §5.3 representation analyses of a run's checkpoint.

    python -m lnnmpc.analysis.report runs/cartpole-swingup/cfc-op-det/<folder> [--checkpoint STEP] [--episodes 10]

Plays deterministic episodes with one seed's agent under the run's evaluation corruptions
(:mod:`lnnmpc.analysis.rollout`) and writes into ``<run>/analysis/<step>/`` (or ``--out``):

* ``correlation.csv`` + ``correlation-<phase>.png``: Pearson r of each true state variable (dm_control's clean
  observation: for cartpole cart position, pole cos/sin, cart and pole velocity) with its ridge prediction
  from [z, z²] (Figures 5.4–5.5); cartpole episodes are split into swing-up and balance phases
  (:func:`lnnmpc.analysis.metrics.balance_start`), other tasks use the whole episode;
* ``umap-<phase>.png``: UMAP of latents and of true states coloured by log |velocity| (Figures 5.6–5.7;
  ``--no-umap`` skips it);
* ``effective_rank.csv`` + ``effective_rank.png``: effective rank of the episodes' hidden-state matrices
  Z (T, N) over training (Figures 5.11–5.12): from the trainer's evaluations (eval.csv's ``effective_rank``,
  every evaluation's episodes) when the run logged it, else by rolling out every checkpoint the run kept
  (``--keep-checkpoints`` of the trainer decides how many there are);
* OP agents: ``prediction_error.csv`` + ``prediction.png``: one-step and k-step (``--k`` 10) observation
  prediction errors, mean ± std over episodes (Tables 5.1–5.2, Figures 5.8–5.9).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from lnnmpc.analysis import metrics
from lnnmpc.train import runfolder
from lnnmpc.train.png import save_png

STATE_NAMES = {"cartpole": ("cart position", "pole cos", "pole sin", "cart velocity", "pole angular velocity")}


def state_names(task: str, dim: int) -> tuple[str, ...]:
    names = STATE_NAMES.get(task.split("-")[0])
    return names if names is not None and len(names) == dim else tuple(f"state {i}" for i in range(dim))


def observation_names(state_names_: tuple, kept, dim: int) -> tuple:
    """Names of the delivered observation's dimensions: the clean observation's names at the indices the
    corruption keeps (``remove_vel`` drops the velocities); () when they do not match ``dim``."""
    kept = [int(i) for i in kept]
    if len(kept) != dim or max(kept, default=-1) >= len(state_names_):
        return ()
    return tuple(state_names_[i] for i in kept)


def phase_masks(task: str, qpos: np.ndarray, threshold: float = 0.3, hold: int = 25) -> dict[str, np.ndarray]:
    """{phase: mask (E, T)}: cartpole swing-up / balance (pole angle qpos[..., 1]), else the whole episode."""
    if not task.startswith("cartpole"):
        return {"all": np.ones(qpos.shape[:2], dtype=bool)}
    starts = [metrics.balance_start(angle, threshold, hold) for angle in qpos[..., 1]]
    steps = np.arange(qpos.shape[1])[None, :]
    balance = steps >= np.asarray(starts)[:, None]
    return {"swingup": ~balance, "balance": balance}


def correlation_rows(latent: np.ndarray, states: np.ndarray, masks: dict, names: tuple, step: int,
                     alpha: float = 1.0) -> tuple[list[dict], dict]:
    """Rows (env_step, phase, variable, r, samples) and {phase: (true (M, K), predicted (M, K))}."""
    rows, fits = [], {}
    for phase, mask in masks.items():
        if mask.sum() < 3:
            continue
        z, s = latent[mask], states[mask]
        r, predicted = metrics.ridge_pearson(z, s, alpha)
        fits[phase] = (s, predicted)
        rows += [{"env_step": step, "phase": phase, "variable": n, "pearson_r": float(v), "samples": int(mask.sum())}
                 for n, v in zip(names, r, strict=True)]
    return rows, fits


def prediction_rows(errors: np.ndarray, k: int) -> list[dict]:
    """Summary of per-episode k-step errors (E, S, k): one-step, step k and the mean over the k steps, each as
    mean ± std over episodes of the episode's mean squared error."""
    per_episode = {"one-step": errors[:, :, 0].mean(axis=1), f"step {k}": errors[:, :, k - 1].mean(axis=1),
                   f"mean over {k} steps": errors.mean(axis=(1, 2))}
    return [{"metric": name, "mean": float(v.mean()), "std": float(v.std()), "episodes": v.size}
            for name, v in per_episode.items()]


def write_csv(path: str, rows: list[dict]) -> None:
    if rows:
        runfolder.write_csv(path, list(rows[0]), rows)


def _figure(rows: int, cols: int, size: float = 3.0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(rows, cols, figsize=(size * cols, size * rows), squeeze=False)
    return plt, fig, axes


def plot_correlation(path: str, true: np.ndarray, predicted: np.ndarray, names: tuple, r: list[float],
                     title: str) -> None:
    """One panel per state variable: ridge predictions from [z, z²] against the truth (``true``, ``predicted``
    (N, len(names))), each titled with its correlation ``r[i]``."""
    plt, fig, axes = _figure(1, len(names))
    for i, ax in enumerate(axes[0]):
        ax.scatter(true[:, i], predicted[:, i], s=3, alpha=0.4)
        ax.set_title(f"{names[i]}\nr = {r[i]:.3f}", fontsize=9)
        ax.set_xlabel("true")
    axes[0, 0].set_ylabel("ridge prediction from [z, z²]")
    fig.suptitle(title)
    fig.tight_layout()
    save_png(fig, path, dpi=110)
    plt.close(fig)


def plot_umap(path: str, latent: np.ndarray, states: np.ndarray, velocities: np.ndarray, title: str,
              seed: int = 0) -> None:
    """2 × V panels: UMAP of latents (top) and of states (bottom), coloured by log |v| of each velocity column."""
    from lnnmpc.analysis.projection import log_speed, umap_2d

    embeddings = {"latent z": umap_2d(latent, seed=seed), "true state": umap_2d(states, seed=seed)}
    plt, fig, axes = _figure(2, velocities.shape[1])
    for row, (label, xy) in enumerate(embeddings.items()):
        for col in range(velocities.shape[1]):
            points = axes[row, col].scatter(xy[:, 0], xy[:, 1], c=log_speed(velocities[:, col]), s=3, cmap="viridis")
            axes[row, col].set_title(f"{label}: log|qvel[{col}]|", fontsize=9)
            fig.colorbar(points, ax=axes[row, col])
    fig.suptitle(title)
    fig.tight_layout()
    save_png(fig, path, dpi=110)
    plt.close(fig)


def plot_series(path: str, x: list[float], y: list[float], yerr: list[float], xlabel: str, ylabel: str,
                title: str | None = None) -> None:
    """One panel: ``y`` ± ``yerr`` against ``x`` (equal lengths), marked at each point."""
    plt, fig, axes = _figure(1, 1, size=4.0)
    axes[0, 0].errorbar(x, y, yerr=yerr, marker="o")
    if title:
        axes[0, 0].set_title(title, fontsize=9)
    axes[0, 0].set_xlabel(xlabel)
    axes[0, 0].set_ylabel(ylabel)
    fig.tight_layout()
    save_png(fig, path, dpi=110)
    plt.close(fig)


def plot_predictions(path: str, targets: np.ndarray, one_step: np.ndarray, rollouts: list, names: tuple) -> None:
    """One episode: observations (solid) vs one-step predictions (dashed), and k-step rollouts every k steps."""
    plt, fig, axes = _figure(2, 1, size=4.0)
    fig.set_size_inches(10, 6)
    for i in range(targets.shape[1]):
        line, = axes[0, 0].plot(targets[:, i], label=names[i] if i < len(names) else f"obs {i}")
        axes[0, 0].plot(np.arange(1, len(one_step) + 1), one_step[:, i], "--", color=line.get_color())
        axes[1, 0].plot(targets[:, i], color=line.get_color())
        for start, values in rollouts:
            axes[1, 0].plot(np.arange(start + 1, start + 1 + len(values)), values[:, i], "--", color=line.get_color())
    axes[0, 0].set_title("one-step predictions (dashed) vs observations")
    axes[1, 0].set_title("k-step rollouts (dashed) vs observations")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    save_png(fig, path, dpi=110)
    plt.close(fig)


def effective_ranks(run: str, steps: list[int], episodes: int, seed_index: int = 0, known: dict | None = None,
                    length: int | None = None, policy=None) -> list[dict]:
    """Effective rank of each episode's Z (T, N), mean ± std over episodes, at each checkpoint step; ``known``
    maps steps to latents (E, T, N) already rolled out; ``length``: agent steps per episode (None: all);
    ``policy``: a loaded :class:`lnnmpc.train.evaluate.Policy` of ``run`` whose compiled rollout is reused."""
    import jax

    from lnnmpc.analysis.rollout import rollout
    from lnnmpc.train.evaluate import load_policy, policy_at

    rows = []
    for step in steps:
        latent = (known or {}).get(step)
        if latent is None:
            policy = load_policy(run, step) if policy is None else policy_at(policy, run, step)
            state = policy.seed_state(seed_index)
            latent = rollout(policy.loop.agent, state, policy.loop.eval_env, jax.random.key(0), episodes,
                             length)["latent"]
        ranks = np.array([metrics.effective_rank(z) for z in latent])
        rows.append({"env_step": step, "effective_rank": float(ranks.mean()), "std": float(ranks.std()),
                     "episodes": len(ranks), "latent_dim": latent.shape[-1]})
    return rows


def ranks_from_eval(run: str, seed_index: int | None, latent_dim: int) -> list[dict]:
    """:func:`effective_ranks`' rows from the trainer's evaluations (eval.csv's ``effective_rank`` of seed
    ``seed_index``, or of every seed pooled when None: mean ± std over the episodes of each evaluation); []
    when the run did not log it."""
    from lnnmpc.train.report import eval_ranks

    pooled: dict[int, list[float]] = {}
    for (seed, step), values in eval_ranks(runfolder.read_csv(os.path.join(run, "eval.csv"))).items():
        if seed_index is None or seed == seed_index:
            pooled.setdefault(step, []).extend(values)
    return [{"env_step": step, "effective_rank": float(np.mean(values)), "std": float(np.std(values)),
             "episodes": len(values), "latent_dim": latent_dim} for step, values in sorted(pooled.items())]


def write_rank_history(run: str, out: str | None = None, seed_index: int | None = None) -> str:
    """Effective rank over training (Figures 5.11–5.12) from eval.csv alone (no checkpoint needed, so it works
    on a results folder): ``effective_rank.csv`` + ``effective_rank.png`` in ``out`` (default
    ``<run>/analysis``); seed ``seed_index``, or all seeds' episodes pooled. Returns the folder."""
    config = runfolder.read_config(run)
    model = config["agent_config"]["model"]
    # the liquid agents' latent is h (hidden_size) unless a SimNorm head widens it (latent_size); TD-MPC2's latent_dim
    latent_dim = model.get("latent_size") or model.get("hidden_size", model.get("latent_dim"))
    rows = ranks_from_eval(run, seed_index, latent_dim)
    if not rows:
        raise ValueError(f"{os.path.join(run, 'eval.csv')} has no effective_rank column (the run predates it); "
                         "run the full report on its checkpoints instead")
    out = out or os.path.join(run, "analysis")
    os.makedirs(out, exist_ok=True)
    seeds = "all seeds" if seed_index is None else f"seed {seed_index}"
    write_ranks(out, rows, f"{config['config']['task']} {config['config']['agent']}, {seeds}")
    return out


def write_ranks(out: str, rows: list[dict], title: str | None = None) -> None:
    """``effective_rank.csv`` and ``effective_rank.png`` (mean ± std per evaluation) of rank rows in ``out``."""
    write_csv(os.path.join(out, "effective_rank.csv"), rows)
    plot_series(os.path.join(out, "effective_rank.png"), [r["env_step"] for r in rows],
                [r["effective_rank"] for r in rows], [r["std"] for r in rows], "environment steps",
                f"effective rank of Z ({rows[0]['latent_dim']} units)" if rows else "effective rank of Z", title)


def analyse(run: str, *, checkpoint: int | None = None, episodes: int = 10, out: str | None = None,
            seed_index: int = 0, k: int = 10, alpha: float = 1.0, use_umap: bool = True, seed: int = 0,
            length: int | None = None) -> str:
    """Writes the analyses of the module docstring for ``run`` at ``checkpoint`` (None: the newest); returns
    the output folder. ``length``: agent steps per episode (None: whole episodes)."""
    import jax

    from lnnmpc.analysis.rollout import op_model_functions, rollout
    from lnnmpc.train.checkpoint import all_steps
    from lnnmpc.train.evaluate import load_policy
    from lnnmpc.train.report import StepProgress

    policy = load_policy(run, checkpoint)
    config, agent = policy.config, policy.loop.agent
    if not 0 <= seed_index < config.seeds:
        raise ValueError(f"seed_index {seed_index} is not one of the run's seeds 0..{config.seeds - 1}")
    out = out or os.path.join(run, "analysis", str(policy.checkpoint))
    os.makedirs(out, exist_ok=True)
    state = policy.seed_state(seed_index)
    rec = rollout(agent, state, policy.loop.eval_env, jax.random.key(seed), episodes, length,
                  StepProgress(f"agent steps of {episodes} episode(s), seed {seed_index}, MJX"))
    names = state_names(config.task, rec["clean_obs"].shape[-1])
    masks = phase_masks(config.task, rec["qpos"])
    rows, fits = correlation_rows(rec["latent"], rec["clean_obs"], masks, names, policy.checkpoint, alpha)
    write_csv(os.path.join(out, "correlation.csv"), rows)
    label = f"{config.task} {config.agent} at {policy.checkpoint:,} env steps"
    for phase, (true, predicted) in fits.items():
        r = [row["pearson_r"] for row in rows if row["phase"] == phase]
        plot_correlation(os.path.join(out, f"correlation-{phase}.png"), true, predicted, names, r,
                         f"{label}, {phase} phase")
        if use_umap:
            mask = masks[phase]
            plot_umap(os.path.join(out, f"umap-{phase}.png"), rec["latent"][mask], rec["clean_obs"][mask],
                      rec["qvel"][mask][:, :2], f"{label}, {phase} phase", seed=seed)
    if getattr(agent.config.model, "objective", None) == "op":
        predict, step = op_model_functions(agent, state)
        errors = np.stack([metrics.k_step_errors(predict, step, z, a, o, k)
                           for z, a, o in zip(rec["latent"], rec["action"], rec["obs"], strict=True)])
        write_csv(os.path.join(out, "prediction_error.csv"), prediction_rows(errors, k))
        z, a, o = rec["latent"][0], rec["action"][0], rec["obs"][0]
        one = metrics.k_step_predictions(predict, step, z, a, np.arange(len(z) - 1), 1)[:, 0]
        starts = np.arange(0, len(z) - k, k)
        rolled = metrics.k_step_predictions(predict, step, z, a, starts, k)
        plot_predictions(os.path.join(out, "prediction.png"), o, one, list(zip(starts, rolled, strict=True)),
                         observation_names(names, policy.loop.eval_env.kept, o.shape[-1]))
    # Last: without the trainer's logged ranks it rolls out every kept checkpoint (the slowest part).
    ranks = ranks_from_eval(run, seed_index, rec["latent"].shape[-1]) or effective_ranks(
        run, all_steps(run), episodes, seed_index, {policy.checkpoint: rec["latent"]}, length, policy)
    write_ranks(out, ranks, f"{config.task} {config.agent}, seed {seed_index}")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lnnmpc.analysis.report", description=__doc__.split("\n")[0])
    p.add_argument("run", help="a run folder")
    p.add_argument("--checkpoint", type=int, default=None, help="env step of a checkpoint (default: newest)")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed-index", type=int, default=None,
                   help="which of the run's seeds to analyse (default 0; --ranks-only: all seeds pooled)")
    p.add_argument("--k", type=int, default=10, help="rollout length of the k-step prediction error")
    p.add_argument("--alpha", type=float, default=1.0, help="ridge regularisation")
    p.add_argument("--length", type=int, default=None, help="agent steps per episode (default: whole episodes)")
    p.add_argument("--no-umap", action="store_true", help="skip the UMAP figures")
    p.add_argument("--out", default=None, help="output folder (default <run>/analysis/<step>)")
    p.add_argument("--ranks-only", action="store_true",
                   help="only the effective rank over training, from eval.csv (no checkpoint needed; all seeds "
                        "pooled unless --seed-index is given; default output <run>/analysis)")
    args = p.parse_args(argv)
    from lnnmpc.train.config import command_status

    if args.ranks_only:
        return command_status(lambda: "wrote " + write_rank_history(args.run, args.out, args.seed_index),
                              errors=(ValueError,))
    return command_status(lambda: "wrote " + analyse(
        args.run, checkpoint=args.checkpoint, episodes=args.episodes, out=args.out, seed_index=args.seed_index or 0,
        k=args.k, alpha=args.alpha, use_umap=not args.no_umap, length=args.length), errors=(ValueError,))


if __name__ == "__main__":
    sys.exit(main())
