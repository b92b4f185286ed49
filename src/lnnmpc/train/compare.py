"""``python -m lnnmpc.train.compare RUN [RUN ...] --out FIG.png``: learning curves of several runs on one plot.

    python -m lnnmpc.train.compare runs/a runs/b --labels "raw inputs" "symlog inputs" --out walker.png
    make compare RUNS="runs/a runs/b" OUT=walker.png

Each run folder's ``eval.csv`` becomes one curve: mean over seeds of each seed's episode mean, shaded ± std over
seeds (over episodes for a one-seed run), as in the run's own ``curve.png``. Where all runs share a task and
evaluation corruption, the thesis's final returns for their agents are drawn as horizontal reference lines.
A CSV beside the figure (same name, ``.csv``) holds the plotted numbers: run, label, column (the eval.csv column
plotted: ``return``, or ``prior_return`` with ``--eval-column``), env_step, mean, std, seeds.

``--metrics value_loss,reward_loss`` adds one panel per ``train.csv`` metric beside the returns: per run, the
median over seeds of the metric at each logged step, shaded between the seeds' minimum and maximum; log scale
where a metric spans more than two decades. A run that does not log a metric (TD-MPC2's ``consistency_loss`` is
the liquid agents' ``prediction_loss``) is left out of that panel; a metric no run logs is refused with the ones
they do. Those numbers go to ``<figure>-metrics.csv`` (run, label, metric, env_step, median, min, max, seeds).

``--pool LABEL`` adds one curve of all the runs' seeds together, at the evaluation steps they all have: runs of one
configuration started with other master seeds (a one-GPU session runs walker one seed per call) read as one run;
runs that differ in anything but how they were launched (:func:`pooling_differences`) are refused, naming it.
To pool some runs only, join them with ``+`` (``runs/a0+runs/a1 runs/b0+runs/b1+runs/b2``: two curves).

``--eval-column prior_return`` plots another column of the evaluation CSVs in place of ``return``: the policy
prior's returns that runs trained with ``--eval-prior`` log beside MPPI's (each run's own ``curve.png`` draws both).
"""

from __future__ import annotations

import argparse
import os
import sys
import textwrap

import numpy as np

from lnnmpc.train import runfolder
from lnnmpc.train.compat import agent_config_changes
from lnnmpc.train.config import RESUMABLE_CHANGES, ConfigError, TrainConfig, command_status
from lnnmpc.train.png import save_png
from lnnmpc.train.references import references
from lnnmpc.train.report import column_rows, eval_table, training_panels


def default_label(config: dict) -> str:
    """``agent`` plus what tells runs apart: corruptions and agent overrides (``cfc-zp-det remove_vel=True``)."""
    c = config["config"]
    parts = [c["agent"]] + [f"{k}={v}" for k, v in c["obs"].items()]
    parts += [f"{k}={v}" for k, v in sorted(c.get("overrides", {}).items())]
    return " ".join(parts)


def load_curves(runs: list[str], labels: list[str] | None = None, evals: str | None = None,
                column: str = "return") -> list[dict]:
    """One entry per run: {"run", "label", "task", "agent", "eval_obs", "table", "rows", "config", "column"} (table:
    :func:`eval_table` rows; rows: eval.csv's own rows, with ``column``'s values as their ``return`` and rows
    without one left out (:func:`lnnmpc.train.report.column_rows`); config: the run's whole config.json). A run
    given as ``a+b+c`` (run folders joined by ``+``, where no folder has that name) is those runs pooled into one
    (:func:`pool_curves`; label by default the first run's, with the pooled seed count). ``evals`` names a CSV
    under each run's ``evals/`` folder (what ``cli eval`` wrote, e.g. ``dm_control-clean-200192.csv``) to read
    instead of the training's ``eval.csv``.

    Raises ConfigError naming a folder that is not a run folder or has no evaluation yet (with ``evals``: the
    files its ``evals/`` holds) or no value in ``column`` (naming its columns), and a label count that does not
    match the runs."""
    if not runs:
        raise ConfigError("give at least one run folder")
    if labels is not None and len(labels) != len(runs):
        raise ConfigError(f"{len(labels)} label(s) for {len(runs)} run(s); give one label per run or none")
    curves = []
    for i, run in enumerate(runs):
        if "+" in run and not os.path.exists(run):
            pooled = pool_curves(load_curves(run.split("+"), evals=evals, column=column), "")
            seeds = len({int(r["seed"]) for r in pooled["rows"]})
            pooled["label"] = labels[i] if labels else f"{default_label(pooled['config'])} ({seeds} seeds pooled)"
            for part in pooled["parts"]:  # (for the per-run tables: speed, commands)
                part["label"] = f"{pooled['label']}: {os.path.basename(os.path.normpath(part['run']))}"
            curves.append(pooled)
            continue
        config = runfolder.read_config(run)
        name = "eval.csv" if evals is None else os.path.join("evals", evals)
        logged = runfolder.read_csv(os.path.join(run, name))
        rows = logged if column == "return" else column_rows(logged, column)
        if logged and not rows:
            raise ConfigError(f"{run!r} logs no {column!r} in {name}; its columns: {', '.join(logged[0])}")
        table = eval_table(rows)
        if not table and evals is not None:
            held = sorted(f for f in os.listdir(os.path.join(run, "evals"))
                          if f.endswith(".csv")) if os.path.isdir(os.path.join(run, "evals")) else []
            raise ConfigError(f"{run!r} has no evaluation rows in evals/{evals}; its evals/ holds "
                              + (", ".join(held) if held else "no CSV (write one with `cli eval`)"))
        if not table:
            raise ConfigError(f"{run!r} has no evaluation rows in eval.csv yet")
        c = config["config"]
        curves.append({"run": run, "label": labels[i] if labels else default_label(config), "task": c["task"],
                       "agent": c["agent"], "eval_obs": c["eval_obs"], "table": table, "rows": rows,
                       "config": config, "column": column})
    return curves


# What runs may differ in and still be pooled, beyond what a resumed run may change (RESUMABLE_CHANGES).
POOLABLE = ("seed", "seeds", "eval_every")


def pooling_differences(a: dict, b: dict) -> list[str]:
    """``"key: a_value != b_value"`` for every setting two runs' config.json contents ``a`` and ``b`` differ in that
    keeps them from being pooled: their :class:`TrainConfig` as a resumed run must keep it
    (:meth:`TrainConfig.resumable_part`; defaults for fields an older run lacks) but for :data:`POOLABLE`, and the
    agent's resolved settings (``agent.``-prefixed; :func:`lnnmpc.train.compat.agent_config_changes`)."""
    config_a, config_b = (TrainConfig.from_dict(c["config"]).resumable_part() for c in (a, b))
    keys = sorted(config_a.keys() | config_b.keys())
    differ = [f"{key}: {config_a.get(key)!r} != {config_b.get(key)!r}" for key in keys
              if key not in POOLABLE and config_a.get(key) != config_b.get(key)]
    return differ + [f"agent.{key}: {x!r} != {y!r}"
                     for key, x, y in agent_config_changes(a.get("agent_config", {}), b.get("agent_config", {}))]


def pool_curves(curves: list[dict], label: str) -> dict:
    """One curve (as :func:`load_curves` gives) of every seed of ``curves``' runs, at the evaluation steps all of
    them have: runs of one configuration started with different master seeds (or seed counts, or device counts)
    read as one run of all their seeds. Seeds are renumbered run after run.

    Raises ConfigError naming the settings two runs differ in (:func:`pooling_differences`), or when the runs share
    no evaluation step."""
    if len(curves) < 2:
        raise ConfigError("--pool needs at least two run folders")
    folders = [os.path.realpath(c["run"]) for c in run_curves(curves)]
    twice = sorted({f for f in folders if folders.count(f) > 1})
    if twice:
        raise ConfigError(f"cannot pool a run with itself: {', '.join(map(repr, twice))} given more than once")
    first = curves[0]
    for curve in curves[1:]:
        differ = pooling_differences(first["config"], curve["config"])
        if differ:
            raise ConfigError(f"cannot pool {first['run']!r} and {curve['run']!r}: they differ in "
                              + "; ".join(differ) + f" (only {', '.join(POOLABLE + RESUMABLE_CHANGES)} may differ, "
                              "overrides where the agent's settings agree)")
    steps = set.intersection(*({int(r["env_step"]) for r in c["rows"]} for c in curves))
    if not steps:
        raise ConfigError("the runs to pool share no evaluation step: " + "; ".join(
            f"{c['run']!r} evaluated at {sorted({int(r['env_step']) for r in c['rows']})}" for c in curves))
    rows, offset = [], 0
    for curve in curves:
        seeds = sorted({int(r["seed"]) for r in curve["rows"]})
        index = {s: offset + i for i, s in enumerate(seeds)}
        rows += [{**r, "seed": index[int(r["seed"])]} for r in curve["rows"] if int(r["env_step"]) in steps]
        offset += len(seeds)
    return {**first, "run": "+".join(c["run"] for c in curves), "label": label, "rows": rows,
            "table": eval_table(rows), "parts": run_curves(curves)}


def run_curves(curves: list[dict]) -> list[dict]:
    """``curves`` with each pooled one (:func:`pool_curves`) replaced by the runs it pools: for what is read per
    run folder (train.csv metrics, timing.csv, the commands)."""
    return [part for curve in curves for part in curve.get("parts", [curve])]


def metric_series(curves: list[dict], metrics: list[str]) -> dict[str, list[dict]]:
    """{metric: one entry per run of ``curves`` (:func:`load_curves`) that logs it: {"run", "label", "env_step",
    "median", "min", "max", "seeds"}} from each run's train.csv (arrays over the logged steps; median, min and max
    over the seeds logging a step).

    Raises ConfigError for a metric that no run logs, naming the metrics they do. A pooled curve
    (:func:`pool_curves`) has no train.csv of its own and is left out."""
    runs = [c["run"] for c in curves]
    panels = {run: training_panels(runfolder.read_csv(os.path.join(run, "train.csv")))
              if os.path.exists(os.path.join(run, "train.csv")) else {} for run in runs}
    known = sorted({name for p in panels.values() for name in p})
    series: dict[str, list[dict]] = {}
    for metric in metrics:
        if not any(metric in p for p in panels.values()):
            raise ConfigError(f"no run logs metric {metric!r} in train.csv; logged: {', '.join(known) or 'nothing'}")
        series[metric] = []
        for run, label in ((c["run"], c["label"]) for c in curves):
            if metric not in panels[run]:
                continue
            by_step: dict[int, list[float]] = {}
            for steps, values in panels[run][metric].values():
                for step, value in zip(steps.tolist(), values.tolist(), strict=True):
                    by_step.setdefault(step, []).append(value)
            steps = sorted(by_step)
            series[metric].append({
                "run": run, "label": label, "env_step": np.asarray(steps),
                "median": np.asarray([np.median(by_step[k]) for k in steps]),
                "min": np.asarray([min(by_step[k]) for k in steps]),
                "max": np.asarray([max(by_step[k]) for k in steps]),
                "seeds": np.asarray([len(by_step[k]) for k in steps])})
    return series


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


def panel_title(title: str, width: int = 55) -> str:
    """``title`` broken at spaces into lines of at most ``width`` characters (a longer word stays whole): the return
    panel is ~5 inches wide, and a longer line ran off the figure's left edge."""
    return textwrap.fill(title, width=width, break_long_words=False, break_on_hyphens=False)


def write_comparison(curves: list[dict], out: str, title: str | None = None,
                     metrics: dict[str, list[dict]] | None = None) -> tuple[str, ...]:
    """Writes the figure ``out`` and its numbers ``<out without extension>.csv`` (with ``metrics``, from
    :func:`metric_series`, one more panel per metric and ``<...>-metrics.csv``); returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    lines = reference_lines(curves)
    metrics = metrics or {}
    # a long legend goes beside the axes instead of over the curves (with metric panels, below the figure)
    outside = len(curves) + len(lines) > 6
    cols = 2 if len(metrics) == 3 else min(3, 1 + len(metrics))
    nrows = -(-(1 + len(metrics)) // cols)
    fig, axes = plt.subplots(nrows, cols, squeeze=False,
                             figsize=((9.5 if outside and not metrics else 7) + 4.2 * (cols - 1),
                                      4.2 * nrows + (1.5 if outside and metrics else 0)))
    ax = axes.flat[0]
    colors = {}
    rows = []
    for curve in curves:
        steps = [t["env_step"] for t in curve["table"]]
        mean = np.asarray([t["mean"] for t in curve["table"]])
        std = np.asarray([t["std"] for t in curve["table"]])
        seeds = curve["table"][-1]["seeds"]
        line, = ax.plot(steps, mean, marker="o", markersize=3,
                        label=f"{curve['label']} ({seeds} seed{'s' if seeds != 1 else ''})")
        colors[curve["run"], curve["label"]] = line.get_color()
        ax.fill_between(steps, mean - std, mean + std, alpha=0.2, color=line.get_color())
        rows += [{"run": curve["run"], "label": curve["label"], "column": curve.get("column", "return"),
                  "env_step": t["env_step"], "mean": t["mean"], "std": t["std"], "seeds": t["seeds"]}
                 for t in curve["table"]]
    for label, value, style in lines:
        ax.axhline(value, linestyle=style, color="gray", linewidth=1, label=f"{label}: {value:.0f}")
    tasks = sorted({c["task"] for c in curves})
    one_seed = any(c["table"][-1]["seeds"] == 1 for c in curves)
    spread = "seeds;\nover episodes for a one-seed run" if one_seed else "seeds"
    column = curves[0].get("column", "return")
    ax.set(xlabel="environment steps", ylabel=f"evaluation {column} (mean ± std over {spread})",
           title=panel_title(title or ", ".join(tasks)), ylim=(0, 1000))
    ax.grid(alpha=0.3)
    if outside and metrics:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.15), ncols=2)
    elif outside:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    else:
        ax.legend(fontsize=7, loc="upper left")
    metric_rows = _draw_metrics(list(axes.flat)[1:], metrics, colors)
    for each in axes.flat:  # 25K, 50K, ...: full step counts run into each other on narrow panels
        each.xaxis.set_major_formatter(lambda x, _: f"{x / 1000:g}K" if x else "0")
    fig.tight_layout()
    save_png(fig, out, dpi=110)
    plt.close(fig)
    table_path = os.path.splitext(out)[0] + ".csv"
    runfolder.write_csv(table_path, list(rows[0]), rows)
    if not metric_rows:
        return out, table_path
    metrics_path = os.path.splitext(out)[0] + "-metrics.csv"
    runfolder.write_csv(metrics_path, list(metric_rows[0]), metric_rows)
    return out, table_path, metrics_path


def _draw_metrics(axes: list, metrics: dict[str, list[dict]], colors: dict) -> list[dict]:
    """One panel per metric on ``axes`` (spare axes hidden); returns the plotted numbers as CSV rows."""
    rows = []
    for ax, (metric, entries) in zip(axes, metrics.items(), strict=False):
        for e in entries:
            color = colors.get((e["run"], e["label"]))
            ax.plot(e["env_step"], e["median"], linewidth=1.2, color=color, label=e["label"])
            ax.fill_between(e["env_step"], e["min"], e["max"], alpha=0.2, color=color)
            rows += [{"run": e["run"], "label": e["label"], "metric": metric, "env_step": int(step),
                      "median": float(mid), "min": float(lo), "max": float(hi), "seeds": int(n)}
                     for step, mid, lo, hi, n in zip(e["env_step"], e["median"], e["min"], e["max"], e["seeds"],
                                                     strict=True)]
        low = min(float(e["min"].min()) for e in entries)
        if low > 0 and max(float(e["max"].max()) for e in entries) > 100 * low:
            ax.set_yscale("log")
        ax.set(xlabel="environment steps", title=f"{metric} (train.csv; median, min-max over seeds)")
        ax.title.set_fontsize(9)
        ax.grid(alpha=0.3)
        if len(entries) < len(colors):
            ax.legend(fontsize=6)  # some runs do not log this metric: say which are drawn
    for ax in axes[len(metrics):]:
        ax.axis("off")
    return rows


def add_pool_and_column_args(parser: argparse.ArgumentParser, pooled: str, verb: str) -> None:
    """``--pool LABEL`` and ``--eval-column NAME``, shared by ``compare`` (``pooled="curve", verb="plot"``) and
    ``tables`` (``"column", "tabulate"``): what the pooled seeds become and what is done with the column."""
    parser.add_argument("--pool", default=None, metavar="LABEL",
                        help=f"also one {pooled} LABEL of every run's seeds together, at the steps all runs "
                        "evaluated (runs of one configuration with other master seeds; refused for runs that "
                        "differ otherwise)")
    parser.add_argument("--eval-column", default="return",
                        help=f"eval.csv column to {verb} (default return: MPPI's; prior_return: the policy prior "
                        "alone, in runs trained with --eval-prior)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lnnmpc.train.compare", description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", help="run folders")
    p.add_argument("--labels", nargs="+", default=None, help="one legend label per run (default: agent, "
                   "corruptions and overrides)")
    p.add_argument("--out", required=True, help="figure path (.png); the numbers go to the same name .csv")
    p.add_argument("--title", default=None)
    p.add_argument("--metrics", default="", help="train.csv metrics to plot beside the returns, comma separated "
                   "(e.g. value_loss,reward_loss,grad_norm)")
    add_pool_and_column_args(p, "curve", "plot")
    args = p.parse_args(argv)

    def compare() -> str:
        curves = load_curves(args.runs, args.labels, column=args.eval_column)
        pooled = [pool_curves(curves, args.pool)] if args.pool is not None else []
        names = [m for m in args.metrics.split(",") if m]
        metrics = metric_series(curves, names) if names else None  # per run (a pooled curve has no train.csv)
        paths = write_comparison(curves + pooled, args.out, args.title, metrics)
        return f"wrote {', '.join(paths[:-1])} and {paths[-1]}"

    return command_status(compare)


if __name__ == "__main__":
    sys.exit(main())
