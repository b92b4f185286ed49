"""What a person looks at: the live progress line, ``curve.png``, ``training.png``, ``summary.md`` and optional
TensorBoard scalars.

Everything here reads the run folder's files (config.json, eval.csv, train.csv), so ``write_reports(run)`` can
redraw a finished or running run at any time (``python -m lnnmpc.train.cli report RUN``).
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from lnnmpc.train import provenance, runfolder
from lnnmpc.train.checkpoint import all_steps
from lnnmpc.train.png import save_png
from lnnmpc.train.references import references


def bar(fraction: float, width: int = 30) -> str:
    """A text progress bar ``[###...]`` of ``width`` cells, ``fraction`` of them (at most all) filled."""
    filled = int(width * min(fraction, 1.0))
    return f"[{'#' * filled}{'.' * (width - filled)}]"


class Progress:
    """One live line on stderr: a bar, environment steps (per seed), the speed over the last chunk (environment
    steps per second per seed; evaluation and checkpoint time included, compilation only on the first chunks)
    and the last evaluation's mean return, with the policy prior's beside it where it was evaluated
    (``eval_prior``)."""

    def __init__(self, total: int):
        self.total, self.last_eval, self.rate = total, float("nan"), float("nan")
        self.last_prior = float("nan")
        self._last: tuple[int, float] | None = None

    def show(self, done: int) -> None:
        now = time.perf_counter()
        if self._last is not None and done > self._last[0]:
            self.rate = (done - self._last[0]) / max(now - self._last[1], 1e-9)
        if self._last is None or done > self._last[0]:
            self._last = (done, now)
        sys.stderr.write("\r" + self.line(done))
        sys.stderr.flush()

    def line(self, done: int) -> str:
        """The progress line after ``done`` environment steps per seed ("—" for a speed or evaluation not yet
        measured, e.g. during the random seed phase)."""
        number = lambda x, fmt, pad: f"{'—':>{pad}}" if np.isnan(x) else f"{x:{pad}{fmt}}"
        prior = "" if np.isnan(self.last_prior) else f" (prior {self.last_prior:.1f})"
        return (f"{bar(done / self.total)} {done:>9,}/{self.total:,} env steps  "
                f"{number(self.rate, '.0f', 8)} steps/s  last eval {number(self.last_eval, '.1f', 7)}{prior}")


class StepProgress:
    """One live line on stderr for work of known length that is not training (e.g. episodes on dm_control): a bar,
    ``done/total`` of ``unit``, the seconds so far and a linear estimate of those left. Redrawn at most every
    ``every`` seconds and at the end, where it ends its line."""

    def __init__(self, unit: str, every: float = 1.0):
        self.unit, self.every = unit, every
        self._start = time.perf_counter()
        self._drawn = -float("inf")

    def __call__(self, done: int, total: int) -> None:
        now = time.perf_counter()
        if done < total and now - self._drawn < self.every:
            return
        self._drawn = now
        sys.stderr.write("\r" + self.line(done, total, now - self._start) + ("\n" if done >= total else ""))
        sys.stderr.flush()

    def line(self, done: int, total: int, elapsed: float) -> str:
        """The line after ``done`` of ``total`` units in ``elapsed`` seconds."""
        left = f"~{elapsed * (total - done) / done:.0f} s left" if 0 < done < total else "done"
        return f"{bar(done / total)} {done:,}/{total:,} {self.unit}  {elapsed:.0f} s, {left}"


def eval_table(rows: list[dict]) -> list[dict]:
    """Per evaluation step: mean and std of the return over seeds (of each seed's episode mean; over episodes
    when there is one seed), min/max over all episodes, the number of seeds and ``per_seed`` ({seed: mean})."""
    table = []
    for step in sorted({int(r["env_step"]) for r in rows}):
        at = [r for r in rows if int(r["env_step"]) == step]
        seeds = sorted({int(r["seed"]) for r in at})
        per_seed = [np.mean([float(r["return"]) for r in at if int(r["seed"]) == s]) for s in seeds]
        returns = [float(r["return"]) for r in at]
        spread = per_seed if len(seeds) > 1 else returns
        table.append({"env_step": step, "mean": float(np.mean(per_seed)), "std": float(np.std(spread)),
                      "min": min(returns), "max": max(returns), "seeds": len(seeds),
                      "per_seed": dict(zip(seeds, map(float, per_seed), strict=True))})
    return table


def column_rows(rows: list[dict], column: str) -> list[dict]:
    """eval.csv ``rows`` with ``column``'s value as their ``return`` (what :func:`eval_table` reads), e.g.
    ``prior_return``; rows whose cell is empty (evaluations before a resumed run turned ``eval_prior`` on) are
    left out."""
    return [{**r, "return": r[column]} for r in rows if r.get(column) not in (None, "")]


def seed_finals(table: list[dict]) -> str | None:
    """One line: each seed's mean at the last evaluation beside its own best evaluation, so that one seed falling
    at the end (and pulling the mean down) stands out; None for a single seed or no evaluation."""
    if not table or table[-1]["seeds"] < 2:
        return None
    parts = []
    for seed, value in table[-1]["per_seed"].items():
        best = max((t for t in table if seed in t["per_seed"]), key=lambda t: t["per_seed"][seed])
        parts.append(f"seed {seed} {value:.1f} (its best {best['per_seed'][seed]:.1f} at {best['env_step']:,})")
    return "Per seed at the last evaluation: " + ", ".join(parts) + "."


def plot_curve(run: str, table: list[dict], refs: dict[str, float], title: str, prior: list[dict] = ()) -> None:
    """Writes curve.png: mean ± std of the evaluation return against environment steps, reference lines, and
    ``prior`` (:func:`eval_table` of the ``prior_return`` column, where the run logs it) as a dashed curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def band(rows: list[dict], alpha: float, **style) -> None:  # mean line and ± std band of eval_table rows
        steps = [t["env_step"] for t in rows]
        mean, std = np.asarray([t["mean"] for t in rows]), np.asarray([t["std"] for t in rows])
        line, = ax.plot(steps, mean, marker="o", markersize=3, **style)
        ax.fill_between(steps, mean - std, mean + std, alpha=alpha, color=line.get_color())

    over = "seeds" if table and table[-1]["seeds"] > 1 else "episodes"
    fig, ax = plt.subplots(figsize=(6.4, 4))
    band(table, 0.25, label=f"this run{', MPPI' if prior else ''} (mean ± std over {over})")
    if prior:
        band(prior, 0.15, linestyle="--", label="the policy prior alone")
    for (label, value), style in zip(refs.items(), ("--", ":"), strict=False):
        ax.axhline(value, linestyle=style, color="gray" if style == "--" else "black", linewidth=1,
                   label=f"{label}: {value:.0f}")
    ax.set(xlabel="environment steps", ylabel="evaluation return", title=title, ylim=(0, 1000))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    save_png(fig, os.path.join(run, "curve.png"), dpi=110)
    plt.close(fig)


TRAINING_LOG_SCALE = ("grad_norm", "prediction_loss", "consistency_loss")  # spans decades: log y axis


Series = dict[int, tuple[np.ndarray, np.ndarray]]  # seed -> (env_steps, values)


def eval_ranks(eval_rows: list[dict]) -> dict[tuple[int, int], list[float]]:
    """{(seed, env_step): the episodes' effective ranks} from eval.csv rows (runs that logged them)."""
    ranks: dict[tuple[int, int], list[float]] = {}
    for r in eval_rows:
        if r.get("effective_rank") not in (None, ""):
            ranks.setdefault((int(r["seed"]), int(r["env_step"])), []).append(float(r["effective_rank"]))
    return ranks


def training_panels(rows: list[dict], eval_rows: list[dict] = ()) -> dict[str, Series]:
    """train.csv rows -> {metric: {seed: (env_steps, values)}} for every logged metric, in column order, then
    ``effective_rank (eval)`` from eval.csv rows: each evaluation's mean over episodes, per seed.

    Blank cells (the seed phase logs returns but no losses) and non-numeric ones are left out; a metric with no
    value at all is dropped."""
    panels = {}
    for name in (k for k in (rows[0] if rows else {}) if k not in ("env_step", "seed")):
        per_seed: dict[int, tuple[list, list]] = {}
        for r in rows:
            try:
                value = float(r.get(name) or "nan")
            except ValueError:
                continue
            if np.isnan(value):
                continue
            steps, values = per_seed.setdefault(int(r["seed"]), ([], []))
            steps.append(int(r["env_step"]))
            values.append(value)
        if per_seed:
            panels[name] = {s: (np.asarray(a), np.asarray(b)) for s, (a, b) in sorted(per_seed.items())}
    ranks = eval_ranks(eval_rows)
    if ranks:
        keys = sorted(ranks)
        panels["effective_rank (eval)"] = {
            seed: (np.asarray([step for s, step in keys if s == seed]),
                   np.asarray([np.mean(ranks[(s, step)]) for s, step in keys if s == seed]))
            for seed in sorted({s for s, _ in keys})}
    return panels


def plot_training(run: str, rows: list[dict], title: str, eval_rows: list[dict] = ()) -> list[str]:
    """Writes training.png: one panel per train.csv metric (episode return, losses, gradient norm, Q scale,
    entropy, the stochastic variants' σ and NLL...) against environment steps, a line per seed; returns the
    metric names drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = training_panels(rows, eval_rows)
    if not panels:
        return []
    cols = 4
    nrows = -(-len(panels) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.2 * cols, 2.4 * nrows), squeeze=False)
    for ax, (name, per_seed) in zip(axes.flat, panels.items(), strict=False):
        for seed, (steps, values) in per_seed.items():
            ax.plot(steps, values, linewidth=1, label=f"seed {seed}")
        if name in TRAINING_LOG_SCALE and all((v > 0).all() for _, v in per_seed.values()):
            ax.set_yscale("log")
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=6)
    fig.suptitle(f"{title}: train.csv (per finished episode)", fontsize=10)
    fig.supxlabel("environment steps", fontsize=9)
    fig.tight_layout()
    save_png(fig, os.path.join(run, "training.png"), dpi=90)
    plt.close(fig)
    return list(panels)


def _agent_size(c: dict) -> str:
    """TD-MPC2's model size; the liquid agents have one (light) configuration, which model_size does not touch."""
    return f"model size {c['model_size']}M" if c["agent"] == "tdmpc2" else "light configuration"


LAST_EVALUATIONS = 3  # summary.md's mean over the latest evaluations


def summary_text(run: str, config: dict, table: list[dict], refs: dict[str, float], extra: dict,
                 prior: list[dict] = ()) -> str:
    """The one-screen summary.md of a run (``prior``: :func:`eval_table` of its ``prior_return`` column, if any)."""
    c = config["config"]
    obs = ", ".join(f"{k}={v}" for k, v in c["obs"].items()) or "none"
    eval_obs = ", ".join(f"{k}={v}" for k, v in c["eval_obs"].items()) or "none"
    done = table[-1]["env_step"] if table else 0
    lines = [f"# {c['task']} · {c['agent']} · {c['seeds']} seed(s)", "",
             f"Run folder `{run}`; settings in `config.json`, returns in `eval.csv`, losses in `train.csv`, "
             "plots `curve.png` (returns) and `training.png` (losses and the rest of `train.csv`).", "",
             "| setting | value |", "|---|---|",
             f"| environment steps | {done:,} of {c['steps']:,} (seed phase {c['seed_steps']:,}) |",
             f"| training corruptions | {obs} |", f"| evaluation corruptions | {eval_obs} |",
             f"| agent | {c['agent']} ({_agent_size(c)}{', small' if c['small'] else ''}"
             f"{', overrides ' + str(c['overrides']) if c['overrides'] else ''}) |",
             f"| physics, envs per seed | {c['physics']}, {c['envs']} |",
             f"| devices | {config.get('num_devices', 1)} × {(config.get('devices') or ['?'])[0]}"
             f"{provenance.driver_note(config.get('provenance', []))} |",
             f"| code | {provenance.code_line(config.get('provenance', []))} |", ""]
    if config.get("provenance"):  # the first start's command (a resume's is `... train --resume <run>`)
        lines += [f"Started by `{config['provenance'][0]['command']}`.", ""]
    if table:
        last, best = table[-1], max(table, key=lambda t: t["mean"])
        lines += [f"**Final return {last['mean']:.1f} ± {last['std']:.1f}** at {last['env_step']:,} env steps "
                  f"(best {best['mean']:.1f} at {best['env_step']:,}).", ""]
        if prior:
            lines += [f"The policy prior alone on the same episodes: {prior[-1]['mean']:.1f} ± {prior[-1]['std']:.1f} "
                      f"at {prior[-1]['env_step']:,} env steps (best {max(t['mean'] for t in prior):.1f}).", ""]
        per_seed = seed_finals(table)
        if per_seed:
            lines += [per_seed, ""]
        if len(table) >= LAST_EVALUATIONS:
            recent = [t["mean"] for t in table[-LAST_EVALUATIONS:]]
            lines += [f"Mean of the last {LAST_EVALUATIONS} evaluations {np.mean(recent):.1f} (from "
                      f"{min(recent):.1f} to {max(recent):.1f}): steadier than one evaluation where the return swings "
                      "between checkpoints.", ""]
        lines += ["| env step | mean | std | min | max |", "|---:|---:|---:|---:|---:|"]
        lines += [f"| {t['env_step']:,} | {t['mean']:.1f} | {t['std']:.1f} | {t['min']:.1f} | {t['max']:.1f} |"
                  for t in table[-6:]]
        lines.append("")
    if refs:
        lines += ["Published: " + "; ".join(f"{k} {v:.1f}" for k, v in refs.items()) + " (thesis Tables 5.3–5.6)."]
    steps = all_steps(run)
    lines.append(f"Checkpoints: {', '.join(f'{s:,}' for s in steps) or 'none'}; resume or extend with "
                 f"`make train RESUME={run} STEPS=...`.")
    if extra.get("train_seconds"):
        lines.append(f"Training time (this machine, incl. compilation): {extra['train_seconds'] / 60:.1f} min.")
    return "\n".join(lines) + "\n"


def write_reports(run: str, extra: dict | None = None, plots: bool = True) -> None:
    """(Re)writes curve.png and training.png (if matplotlib is installed and ``plots``) and summary.md from the run
    folder's files."""
    config = runfolder.read_config(run)
    c = config["config"]
    eval_rows = runfolder.read_csv(os.path.join(run, "eval.csv"))
    table, prior = eval_table(eval_rows), eval_table(column_rows(eval_rows, "prior_return"))
    refs = references(c["task"], c["agent"], c["eval_obs"])
    if plots:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            sys.stderr.write("matplotlib is not installed: no curve.png\n")
        else:
            if table:
                plot_curve(run, table, refs, f"{c['task']} · {c['agent']}", prior)
            plot_training(run, runfolder.read_csv(os.path.join(run, "train.csv")), f"{c['task']} · {c['agent']}",
                          eval_rows)
    runfolder.write_text(os.path.join(run, "summary.md"), summary_text(run, config, table, refs, extra or {}, prior))


def eval_scalars(rows: list[dict]) -> dict[str, float]:
    """One evaluation's rows (all seeds and episodes) -> the scalars the loggers plot: return mean and std, and
    the mean effective rank and policy prior's return where the rows carry them."""
    scalars = {"eval/return_mean": float(np.mean([r["return"] for r in rows])),
               "eval/return_std": float(np.std([r["return"] for r in rows]))}
    for name in ("effective_rank", "prior_return"):
        if name in rows[0]:
            scalars[f"eval/{name}_mean"] = float(np.mean([r[name] for r in rows]))
    return scalars


class ScalarLogger:
    """TensorBoard scalars under ``<run>/tensorboard`` (needs ``tensorboardX``; written locally, no network)."""

    def __init__(self, run: str):
        try:
            from tensorboardX import SummaryWriter
        except ImportError:
            raise RuntimeError("tensorboard=True needs the tensorboardX package: pip install tensorboardX") from None
        self.writer = SummaryWriter(os.path.join(run, "tensorboard"))

    def train_rows(self, rows: list[dict]) -> None:
        for row in rows:
            for key, value in row.items():
                if key not in ("env_step", "seed"):
                    self.writer.add_scalar(f"train/{key}/seed{row['seed']}", value, row["env_step"])

    def eval_rows(self, rows: list[dict]) -> None:
        if rows:
            for name, value in eval_scalars(rows).items():
                self.writer.add_scalar(name, value, rows[0]["env_step"])

    def close(self) -> None:
        self.writer.close()


class WandbLogger:
    """The same scalars to a Weights & Biases project (needs ``wandb``; ``WANDB_MODE=offline`` needs no network).

    The W&B run's id is derived from the run folder, so a resumed run continues the same W&B run; every scalar is
    plotted against ``env_step``. W&B's own files go to ``<run>/wandb``.
    """

    def __init__(self, run: str, project: str, config: dict):
        import hashlib

        try:
            import wandb
        except ImportError:
            raise RuntimeError("wandb logging needs the wandb package: pip install wandb") from None
        folder = os.path.abspath(run)
        run_id = hashlib.sha1(folder.encode()).hexdigest()[:16]
        self.run = wandb.init(project=project, name=os.path.basename(folder), id=run_id, resume="allow",
                              dir=folder, config=config)
        self.run.define_metric("env_step")
        self.run.define_metric("*", step_metric="env_step")

    def train_rows(self, rows: list[dict]) -> None:
        for row in rows:
            self.run.log({"env_step": row["env_step"], **{f"train/{k}/seed{row['seed']}": v for k, v in row.items()
                                                          if k not in ("env_step", "seed")}})

    def eval_rows(self, rows: list[dict]) -> None:
        if rows:
            self.run.log({"env_step": rows[0]["env_step"], **eval_scalars(rows)})

    def close(self) -> None:
        """Finishes the W&B run and waits for W&B's service to write everything out: ``finish`` alone has
        returned with the offline ``.wandb`` file still holding only its header (wandb 0.31, a loaded machine).
        ``wandb.teardown`` ends every W&B run of this process, so close the logger last."""
        import wandb

        self.run.finish()
        wandb.teardown()
