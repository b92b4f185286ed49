"""A study's figure beside its table: our returns and the thesis's, drawn from the study's rows.

:func:`write_study_figure` draws ``<out>/<NAME>.png`` from the rows that
:func:`lnnmpc.experiments.aggregate.study_rows` builds (the numbers of the CSV; a planning-horizon study reads its
runs' per-episode evaluation files). The series come from pure functions, which the tests check:

* :func:`sweep_series`: conditions evaluated under several noise levels (Tables 5.4–5.6) become one panel each,
  return against the evaluation σ, ours as mean ± std over seeds × episodes, the thesis's as a dashed line;
* :func:`bar_series`: conditions evaluated under one setting (Table 5.3, Table 5.4's no-velocity column,
  Figure 5.18's delays) become grouped bars, one group per condition and one bar per agent, the thesis's value
  as a marker on the bar;
* :func:`horizon_samples`: Figure 5.19's per-episode returns and planning times per H_plan from the runs'
  evaluation files, drawn as violins (the thesis draws kernel density estimates of the same samples).

Cells measured before the budget carry their environment step in the label, so a partial run never reads as
a 200K result; cells not yet run are left out.
"""

from __future__ import annotations

import re

import numpy as np

from lnnmpc.experiments.aggregate import newest_eval, read_returns
from lnnmpc.experiments.grid import RunSpec, Study
from lnnmpc.experiments.thesis import AGENT_ORDER
from lnnmpc.train.png import save_png


def _noise(tag: str) -> float | None:
    match = re.search(r"noise([0-9.]+)", tag)
    return float(match.group(1)) if match else None


def _measured(row: dict) -> bool:
    return row["mean"] != ""


def _float(value) -> float:
    return float("nan") if value == "" else float(value)


def _agents(rows: list[dict]) -> list[str]:
    present = {r["agent"] for r in rows}
    return [a for a in AGENT_ORDER if a in present] + sorted(present - set(AGENT_ORDER))


def _conditions(rows: list[dict]) -> dict[tuple[str, str], list[dict]]:
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["task"], row["train_obs"]), []).append(row)
    return groups


def _cells(rows: list[dict | None]) -> dict[str, list[float]]:
    """Ours (mean, std) and the thesis's mean of each row, NaN for a missing row or value."""
    return {key: [_float(r[field]) if r else float("nan") for r in rows]
            for key, field in (("mean", "mean"), ("std", "std"), ("thesis", "thesis_mean"))}


def sweep_series(rows: list[dict]) -> dict[tuple[str, str], dict[str, dict]]:
    """{(task, train tag): {agent: {"sigma", "mean", "std", "thesis", "env_step"}}} for every condition with more
    than one evaluation noise level. Lists follow increasing σ; ``mean``/``std`` are NaN where not measured,
    ``thesis`` NaN where the thesis has no value; ``env_step`` is the smallest step among the measured points
    (None when nothing is measured)."""
    out = {}
    for condition, group in _conditions(rows).items():
        levels = sorted({s for s in (_noise(r["eval_obs"]) for r in group) if s is not None})
        if len(levels) < 2:
            continue
        out[condition] = {}
        for agent in _agents(group):
            by_sigma = {_noise(r["eval_obs"]): r for r in group if r["agent"] == agent}
            points = [by_sigma.get(s) for s in levels]
            steps = [int(p["env_step"]) for p in points if p is not None and _measured(p)]
            out[condition][agent] = {"sigma": levels, **_cells(points), "env_step": min(steps) if steps else None}
    return out


def bar_series(rows: list[dict]) -> tuple[list[tuple[str, str]], dict[str, dict]]:
    """(conditions, {agent: {"mean", "std", "thesis", "env_step"}}) for the conditions evaluated under exactly
    one setting, conditions in row order; each list has one entry per condition (NaN / None where missing)."""
    groups = {c: g for c, g in _conditions(rows).items() if len({r["eval_obs"] for r in g}) == 1}
    conditions = list(groups)
    series = {}
    for agent in _agents([r for g in groups.values() for r in g]):
        cells = [next((r for r in groups[c] if r["agent"] == agent), None) for c in conditions]
        series[agent] = {**_cells(cells), "env_step": [int(r["env_step"]) if r and _measured(r) else None
                                                       for r in cells]}
    return conditions, series


def horizon_samples(specs: list[RunSpec], backend: str = "mjx") -> dict[int, tuple[np.ndarray, np.ndarray, int]]:
    """{H_plan: (returns (seeds·episodes,), planner ms (n,), env step)} from the newest planning-horizon
    evaluation files of a horizon study's runs (horizons without a file are left out)."""
    out = {}
    for spec in specs:
        for obs in spec.condition.eval_obs:
            for horizon in spec.horizons:
                path = newest_eval(spec.folder, obs, backend, horizon)
                if path is not None:
                    step, returns, timing = read_returns(path)
                    out[horizon] = (returns.reshape(-1), np.asarray([] if timing is None else timing), step)
    return dict(sorted(out.items()))


def _steps_label(step: int | None, budget: int) -> str:
    if step is None or step >= budget:
        return ""
    return f" ({step / 1000:.0f}K)"


def write_study_figure(study: Study, specs: list[RunSpec], rows: list[dict], out: str, budget: int,
                       backend: str = "mjx") -> str | None:
    """Draws ``out`` (PNG) for the study's runs ``specs`` and their ``rows``; returns its path, or None when
    nothing is measured yet."""
    if not any(_measured(r) for r in rows):
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if study.horizons:
        fig = _draw_horizons(plt, horizon_samples(specs, backend), rows[0]["task"], rows[0]["agent"])
        fig.suptitle(f"{study.source} ({study.name}): returns and planning time per horizon", fontsize=10)
    else:
        fig = _draw_tables(plt, sweep_series(rows), bar_series(rows), budget)
        thesis = any(r["thesis_mean"] != "" for r in rows if _measured(r))
        fig.suptitle(f"{study.source} ({study.name}): " + ("ours (solid), the thesis's (dashed / black ticks)"
                     if thesis else "ours (the thesis prints no numbers for it)"), fontsize=10)
    fig.tight_layout()
    save_png(fig, out, dpi=110)
    plt.close(fig)
    return out


def _draw_tables(plt, sweeps: dict, bars: tuple[list, dict], budget: int):
    """Line panels of the noise sweeps and one bar panel of the single-setting conditions, each drawn only when
    one of its agents is measured (the table lists the thesis's values of the agents we have not run)."""
    sweeps = {c: {a: s for a, s in agents.items() if s["env_step"] is not None} for c, agents in sweeps.items()}
    sweeps = {c: agents for c, agents in sweeps.items() if agents}
    conditions, series = bars
    series = {a: s for a, s in series.items() if any(step is not None for step in s["env_step"])}
    panels = len(sweeps) + (1 if series else 0)
    fig, axes = plt.subplots(1, panels, figsize=(max(6.5, 4.6 * panels + 1.5 * len(conditions)), 4), squeeze=False)
    axes = list(axes[0])
    colours = {agent: f"C{i}" for i, agent in enumerate(AGENT_ORDER)}
    for ax, ((task, train), agents) in zip(axes, sweeps.items(), strict=False):  # the bar panel, if any, is last
        for agent, s in agents.items():
            colour = colours.get(agent, "k")
            ax.errorbar(s["sigma"], s["mean"], yerr=s["std"], color=colour, marker="o", capsize=3,
                        label=agent + _steps_label(s["env_step"], budget))
            ax.plot(s["sigma"], s["thesis"], color=colour, linestyle="--", marker="o", fillstyle="none")
        ax.set(title=f"{task}, trained {train}", xlabel="evaluation noise σ", ylabel="return", ylim=(0, 1000))
        ax.legend(fontsize=7)
    if series:
        ax, width, x = axes[-1], 0.8 / len(series), np.arange(len(conditions))
        for i, (agent, s) in enumerate(series.items()):
            pos = x - 0.4 + width * (i + 0.5)
            ax.bar(pos, s["mean"], width, yerr=s["std"], capsize=2, label=agent, color=colours.get(agent, "k"))
            ax.scatter(pos, s["thesis"], color="k", marker="_", s=300, linewidths=2.5, zorder=3)
            for p, step in zip(pos, s["env_step"], strict=True):
                if step is not None and step < budget:
                    ax.text(p, 10, f"{step / 1000:.0f}K", rotation=90, ha="center", va="bottom", fontsize=7,
                            color="w")
        ax.set_xticks(x, [f"{t}\n{tr}" for t, tr in conditions], fontsize=7)
        ax.set(ylabel="return", ylim=(0, 1000), xlim=(-0.6, len(conditions) - 0.4),
               title="bars: ours (K: steps reached if short of the budget)")
        ax.legend(fontsize=7)
    return fig


def _draw_horizons(plt, samples: dict, task: str, agent: str):
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    horizons = list(samples)
    for ax, index, label in ((left, 0, "return"), (right, 1, "planner ms per decision")):
        data = [samples[h][index] for h in horizons]
        keep = [i for i, d in enumerate(data) if len(d) > 1 and np.ptp(d) > 0]
        if keep:
            ax.violinplot([data[i] for i in keep], positions=keep, showmeans=True)
        for i, d in enumerate(data):
            ax.scatter(np.full(len(d), i), d, s=8, color="k", alpha=0.5)
        ax.set_xticks(range(len(horizons)), [str(h) for h in horizons])
        ax.set(xlabel="planning horizon H_plan", ylabel=label)
    steps = sorted({s[2] for s in samples.values()})
    left.set_title(f"{task}, {agent}, checkpoint {', '.join(f'{s:,}' for s in steps)}")
    right.set_title("time of one planning decision")
    return fig
