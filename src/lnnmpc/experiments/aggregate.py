"""Aggregation of a study's evaluations into one CSV and one Markdown table beside the thesis's numbers.

Each (run, evaluation corruption[, planning horizon]) becomes one row: the newest evaluation file of the run for
that setting (``evals/<backend>-<tag>-<step>.csv`` or ``evals/horizon<H>-<tag>-<step>.csv``), its environment
step, the number of seeds and episodes (a table row with no plain evaluation takes the run's planning-horizon
evaluation at the horizon it was trained with: the same episodes by the same policy, e.g. Table 5.3's acrobot
cfc-zp-det run, which Figure 5.19's study trains and evaluates), and

* ``mean``: over all seeds × episodes;
* ``std``: over all seeds × episodes (pooled; the thesis's ± is over its 10 episodes);
* ``std_seeds``: over the seeds' mean returns (0 with one seed);
* ``planner_ms`` / ``planner_ms_std`` (horizon rows): median and std of the time of one planning decision;

beside the thesis's value for the agent and the TD-MPC2 entry of the same thesis table
(:mod:`lnnmpc.experiments.thesis`). A setting without an evaluation file is written as "not yet run".
"""

from __future__ import annotations

import csv
import glob
import os
import re

import numpy as np

from lnnmpc.experiments.grid import RunSpec, Study, eval_file, run_status
from lnnmpc.experiments.thesis import tdmpc2_value, thesis_value
from lnnmpc.train import runfolder
from lnnmpc.train.config import obs_tag, parse_obs

FIELDS = ("study", "source", "task", "train_obs", "eval_obs", "agent", "horizon", "status", "run", "env_step",
          "seeds", "episodes", "mean", "std", "std_seeds", "planner_ms", "planner_ms_std", "thesis_mean",
          "thesis_std", "thesis_source", "tdmpc2_mean", "tdmpc2_std", "recipe")
NOT_RUN = "not yet run"


def summarize(returns: np.ndarray) -> dict:
    """Mean and stds of returns (seeds, episodes): pooled std over all, and over the seeds' means."""
    returns = np.asarray(returns, dtype=np.float64)
    if returns.ndim != 2 or returns.size == 0:
        raise ValueError(f"returns must be a non-empty (seeds, episodes) array, got shape {returns.shape}")
    per_seed = returns.mean(axis=1)
    return {"seeds": returns.shape[0], "episodes": returns.shape[1], "mean": float(returns.mean()),
            "std": float(returns.std()), "std_seeds": float(per_seed.std())}


def read_returns(path: str) -> tuple[int, np.ndarray, np.ndarray | None]:
    """(env_step, returns (seeds, episodes), planner_ms (n,) or None) of an evaluation CSV."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} has no rows")
    seeds = sorted({int(r["seed"]) for r in rows})
    episodes = sorted({int(r["episode"]) for r in rows})
    returns = np.full((len(seeds), len(episodes)), np.nan)
    for r in rows:
        returns[seeds.index(int(r["seed"])), episodes.index(int(r["episode"]))] = float(r["return"])
    if np.isnan(returns).any():
        raise ValueError(f"{path} lacks some (seed, episode) pairs of seeds {seeds} x episodes {episodes}")
    timing = [float(r["planner_ms"]) for r in rows if r.get("planner_ms")]
    return int(rows[0]["env_step"]), returns, np.asarray(timing) if timing else None


def _newest_step_eval(folder: str, obs: str, backend: str, horizon: int | None) -> tuple[int, str] | None:
    """(step, path) of the evaluation file of the largest checkpoint step for this setting, or None."""
    pattern = eval_file(folder, 0, obs, backend, horizon)[: -len("0.csv")]
    found = []
    for path in glob.glob(glob.escape(pattern) + "*.csv"):
        match = re.fullmatch(r"(\d+)\.csv", path[len(pattern):])
        if match:
            found.append((int(match.group(1)), path))
    return max(found) if found else None


def newest_eval(folder: str, obs: str, backend: str, horizon: int | None) -> str | None:
    """The evaluation file of the largest checkpoint step for this setting, or None."""
    newest = _newest_step_eval(folder, obs, backend, horizon)
    return newest[1] if newest else None


def trained_plan_horizon(folder: str) -> int | None:
    """The planning horizon a run acted with (its saved agent config), or None when the run does not say."""
    try:
        planner = (runfolder.read_config(folder).get("agent_config") or {}).get("planner") or {}
    except (OSError, ValueError):
        return None
    horizon = planner.get("horizon")
    return horizon if isinstance(horizon, int) else None


def table_eval(folder: str, obs: str, backend: str) -> str | None:
    """The newest evaluation a table row reads: the plain one (``<backend>-<tag>-<step>.csv``) or, on MJX, the
    planning-horizon one at the run's own horizon (identical protocol: ``evaluate_horizon`` with the trained
    horizon replays the policy ``lnnmpc.evaluate`` would); the larger step wins, the plain file on a tie."""
    plain = _newest_step_eval(folder, obs, backend, None)
    horizon = trained_plan_horizon(folder) if backend == "mjx" else None
    trained = _newest_step_eval(folder, obs, backend, horizon) if horizon is not None else None
    if plain and trained and trained[0] > plain[0]:
        return trained[1]
    newest = plain or trained
    return newest[1] if newest else None


def study_rows(study: Study, specs: list[RunSpec], steps: int, backend: str = "mjx") -> list[dict]:
    """One row per run × evaluation corruption (× planning horizon), in grid order."""
    rows = []
    for spec in specs:
        for obs in spec.condition.eval_obs:
            for horizon in spec.horizons or (None,):
                rows.append(_row(study, spec, obs, horizon, steps, backend))
    return rows


def _row(study: Study, spec: RunSpec, obs: str, horizon: int | None, steps: int, backend: str) -> dict:
    task = spec.condition.task
    row = {key: "" for key in FIELDS}
    row.update(study=study.name, source=study.source, task=task, train_obs=obs_tag(parse_obs(spec.condition.train_obs)),
               eval_obs=obs_tag(parse_obs(obs)), agent=spec.agent, horizon="" if horizon is None else horizon,
               status=run_status(spec.folder, steps), run=spec.folder, recipe=spec.recipe)
    if horizon is None:  # the thesis's tables have no per-horizon numbers
        for prefix, ref in (("thesis", thesis_value(task, obs, spec.agent)), ("tdmpc2", tdmpc2_value(task, obs))):
            if ref is not None:
                row[f"{prefix}_mean"], row[f"{prefix}_std"] = ref.mean, "" if ref.std is None else ref.std
                row["thesis_source"] = ref.source
    path = table_eval(spec.folder, obs, backend) if horizon is None else newest_eval(spec.folder, obs, backend, horizon)
    if path is None:
        return row
    step, returns, timing = read_returns(path)
    row.update(env_step=step, **summarize(returns))
    if timing is not None:
        row.update(planner_ms=float(np.median(timing)), planner_ms_std=float(timing.std()))
    return row


def write_csv(path: str, rows: list[dict]) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    runfolder.write_csv(path, FIELDS, rows)


def _pm(mean, std) -> str:
    if mean == "":
        return "—"
    return f"{float(mean):.1f}" if std == "" else f"{float(mean):.1f} ± {float(std):.1f}"


def markdown(study: Study, rows: list[dict]) -> str:
    """The study's Markdown table: ours (mean ± pooled std, and the std over seeds) beside the thesis."""
    timed = bool(study.horizons)
    head = ["task", "trained", "evaluated", "agent"] + (["H_plan"] if timed else []) + [
        "env steps", "seeds × episodes", "ours", "std over seeds"] + (
        ["planner ms / decision"] if timed else ["thesis", "TD-MPC2 (thesis table)"])
    lines = [f"### {study.source} ({study.name})", "", "| " + " | ".join(head) + " |",
             "|" + "|".join("---" if i < 4 else "---:" for i in range(len(head))) + "|"]
    for r in rows:
        agent = r["agent"] + (f" (recipe `{r['recipe']}`)" if r.get("recipe") else "")
        cells = [r["task"], r["train_obs"], r["eval_obs"], agent] + ([str(r["horizon"])] if timed else [])
        if r["mean"] == "":
            cells += [NOT_RUN if r["status"] == "new" else f"{NOT_RUN} ({r['status']})", "", "", ""]
        else:
            cells += [f"{int(r['env_step']):,}", f"{r['seeds']} × {r['episodes']}", _pm(r["mean"], r["std"]),
                      f"{float(r['std_seeds']):.1f}"]
        if timed:
            cells.append(_pm(r["planner_ms"], r["planner_ms_std"]))
        else:
            cells += [_pm(r["thesis_mean"], r["thesis_std"]), _pm(r["tdmpc2_mean"], r["tdmpc2_std"])]
        lines.append("| " + " | ".join(cells) + " |")
    notes = ["", "ours: mean ± std over all seeds × episodes of the newest checkpoint's evaluation; "
             "thesis: its value for the agent; TD-MPC2: the TD-MPC2 entry of the same thesis table (Table 5.3: "
             "TD-MPC2's published 200K result as the thesis quotes it; Tables 5.4–5.6: the thesis's own run)."]
    if timed:
        notes = ["", "ours: mean ± std over seeds × episodes; planner: median ± std of one planning decision "
                 "(one environment, after compilation). The thesis gives Figure 5.19 as plots only."]
    return "\n".join(lines + notes) + "\n"
