"""``lnnmpc.train.compare``: several runs' learning curves on one figure, with the plotted numbers as CSV."""

from __future__ import annotations

import csv
import json
import os

import pytest

from lnnmpc.train import runfolder
from lnnmpc.train.compare import load_curves, main, metric_series, panel_title, reference_lines, shared_references
from lnnmpc.train.config import ConfigError, TrainConfig


def _run(path, agent: str, returns: dict[int, list[list[float]]], **config) -> str:
    """A run folder with config.json and eval.csv: returns[step][seed] = that seed's episode returns."""
    os.makedirs(path)
    runfolder.write_config(str(path), TrainConfig(task="cartpole-swingup", agent=agent, out=str(path), **config), {})
    rows = [{"env_step": step, "seed": seed, "episode": e, "return": r}
            for step, seeds in returns.items() for seed, episodes in enumerate(seeds) for e, r in enumerate(episodes)]
    runfolder.write_csv(os.path.join(path, "eval.csv"), ["env_step", "seed", "episode", "return"], rows)
    return str(path)


def test_compare_plots_each_run_and_writes_the_numbers(tmp_path):
    a = _run(tmp_path / "a", "tdmpc2", {10000: [[100, 300], [500, 500]], 20000: [[600, 600], [800, 800]]}, seeds=2)
    b = _run(tmp_path / "b", "cfc-zp-det", {10000: [[50], [150]]}, seeds=2, overrides={"input_transform": "symlog"})
    curves = load_curves([a, b])
    assert [c["label"] for c in curves] == ["tdmpc2", "cfc-zp-det input_transform=symlog"]
    # mean over seeds of each seed's mean; std over the seed means
    assert [(t["env_step"], t["mean"], t["std"]) for t in curves[0]["table"]] == [(10000, 350.0, 150.0),
                                                                               (20000, 700.0, 100.0)]
    assert set(shared_references(curves)) == {"thesis TD-MPC2", "thesis CfC ZP det"}
    out = str(tmp_path / "fig" / "curves.png")
    assert main([a, b, "--labels", "baseline", "liquid", "--out", out]) == 0
    assert os.path.getsize(out) > 10_000
    with open(str(tmp_path / "fig" / "curves.csv")) as f:
        rows = list(csv.DictReader(f))
    assert [(r["label"], r["env_step"], float(r["mean"])) for r in rows] == [
        ("baseline", "10000", 350.0), ("baseline", "20000", 700.0), ("liquid", "10000", 100.0)]


def test_compare_breaks_a_long_title_into_lines_that_fit_the_panel():
    assert panel_title("acrobot-swingup, cfc-zp-det") == "acrobot-swingup, cfc-zp-det"
    long = "acrobot-swingup, acrobot recipe (action repeat 4): 2 / 3 updates per agent step"
    lines = panel_title(long).split("\n")
    assert len(lines) == 2 and all(len(line) <= 55 for line in lines)
    assert " ".join(lines) == long  # broken at spaces only, nothing lost
    assert panel_title("x" * 70) == "x" * 70  # a word longer than the width stays whole


def test_compare_pools_one_configurations_runs_into_one_more_curve(tmp_path, capsys):
    a = _run(tmp_path / "a", "tdmpc2", {10000: [[100, 300], [500, 500]], 20000: [[600, 600], [800, 800]]}, seeds=2)
    b = _run(tmp_path / "b", "tdmpc2", {10000: [[0, 0]], 30000: [[900, 900]]}, seeds=1, seed=7)
    out = str(tmp_path / "pooled.png")
    assert main([a, b, "--labels", "A", "B", "--pool", "A+B", "--metrics", "", "--out", out]) == 0
    with open(str(tmp_path / "pooled.csv")) as f:
        rows = [r for r in csv.DictReader(f) if r["label"] == "A+B"]
    # only the step both runs evaluated; seed means 200 / 500 / 0: mean 233.3, std over seeds 205.5
    assert [(r["env_step"], round(float(r["mean"]), 1), round(float(r["std"]), 1), r["seeds"]) for r in rows] == [
        ("10000", 233.3, 205.5, "3")]
    c = _run(tmp_path / "c", "cfc-zp-det", {10000: [[1.0]]})
    assert main([a, c, "--pool", "x", "--out", out]) == 2
    assert "differ in agent: 'tdmpc2' != 'cfc-zp-det'" in capsys.readouterr().err
    # "+" pools some runs only: the pooled pair and c as two curves
    assert main([f"{a}+{b}", c, "--labels", "A+B", "C", "--out", out]) == 0
    with open(str(tmp_path / "pooled.csv")) as f:
        rows = [(r["label"], r["env_step"], round(float(r["mean"]), 1), r["seeds"]) for r in csv.DictReader(f)]
    assert rows == [("A+B", "10000", 233.3, "3"), ("C", "10000", 1.0, "1")]


def test_compare_refuses_bad_input_with_the_reason(tmp_path, capsys):
    a = _run(tmp_path / "a", "tdmpc2", {10000: [[1.0]]})
    with pytest.raises(ConfigError, match="1 label\\(s\\) for 2 run\\(s\\)"):
        load_curves([a, a], ["only one"])
    with pytest.raises(ConfigError, match="is not a run folder"):
        load_curves([str(tmp_path)])
    empty = _run(tmp_path / "empty", "tdmpc2", {})
    assert main([empty, "--out", str(tmp_path / "x.png")]) == 2
    assert "has no evaluation rows in eval.csv yet" in capsys.readouterr().err
    other = _run(tmp_path / "other", "tdmpc2", {10000: [[1.0]]}, obs="remove_vel=1")
    assert shared_references(load_curves([a, other])) == {}  # different corruptions: no common reference


def test_compare_draws_every_reference_of_eight_variants(tmp_path):
    variants = [f"{c}-{k}-{n}" for c in ("cfc", "ltc") for k in ("zp", "op") for n in ("det", "stoch")]
    runs = [_run(tmp_path / v, v, {10000: [[100.0, 200.0]]}) for v in variants]
    lines = reference_lines(load_curves(runs))
    # TD-MPC2 plus each variant the thesis reports on cartpole-swingup: none is dropped past the fourth style
    assert [label for label, _, _ in lines] == list(shared_references(load_curves(runs)))
    assert len(lines) > 4 and "thesis LTC OP stoch" in [label for label, _, _ in lines]
    assert lines[4][2] == lines[0][2]  # styles repeat
    assert main(runs + ["--out", str(tmp_path / "eight.png")]) == 0


def _train_csv(run: str, rows: list[tuple[int, int, dict]]) -> None:
    """train.csv of (env_step, seed, metrics) rows; blank cells where a row lacks a column."""
    fields = ["env_step", "seed"] + sorted({k for _, _, m in rows for k in m})
    runfolder.write_csv(os.path.join(run, "train.csv"), fields,
                        [{"env_step": s, "seed": seed, **m} for s, seed, m in rows])


def test_compare_metric_panels_median_and_range_over_seeds(tmp_path, capsys):
    a = _run(tmp_path / "a", "tdmpc2", {10000: [[1.0], [2.0]]}, seeds=2)
    b = _run(tmp_path / "b", "cfc-zp-det", {10000: [[1.0]]})
    _train_csv(a, [(5000, 0, {"value_loss": 0.2, "consistency_loss": 1e-5}),
                   (5000, 1, {"value_loss": 0.4, "consistency_loss": 2e-5}),
                   (9000, 0, {"value_loss": 0.3, "consistency_loss": ""})])
    _train_csv(b, [(5000, 0, {"value_loss": 0.8, "prediction_loss": 3e-4})])
    curves = load_curves([a, b], ["A", "B"])
    series = metric_series(curves, ["value_loss", "consistency_loss"])
    va, vb = series["value_loss"]
    assert va["env_step"].tolist() == [5000, 9000] and va["median"].tolist() == pytest.approx([0.3, 0.3])
    assert (va["min"].tolist(), va["max"].tolist(), va["seeds"].tolist()) == ([0.2, 0.3], [0.4, 0.3], [2, 1])
    assert vb["label"] == "B" and vb["median"].tolist() == [0.8]
    assert [e["label"] for e in series["consistency_loss"]] == ["A"]  # B logs prediction_loss instead
    with pytest.raises(ConfigError, match="no run logs metric 'q_loss'.*logged: consistency_loss, prediction_loss, "
                                          "value_loss"):
        metric_series(curves, ["q_loss"])
    out = str(tmp_path / "m.png")
    assert main([a, b, "--metrics", "value_loss,prediction_loss", "--out", out]) == 0
    assert "m-metrics.csv" in capsys.readouterr().out and os.path.getsize(out) > 10_000
    with open(str(tmp_path / "m-metrics.csv")) as f:
        rows = list(csv.DictReader(f))
    assert [(r["label"], r["metric"], r["env_step"], float(r["median"]), r["seeds"]) for r in rows] == [
        ("tdmpc2", "value_loss", "5000", pytest.approx(0.3), "2"), ("tdmpc2", "value_loss", "9000", 0.3, "1"),
        ("cfc-zp-det", "value_loss", "5000", 0.8, "1"), ("cfc-zp-det", "prediction_loss", "5000", 3e-4, "1")]
    assert main([a, "--metrics", "nope", "--out", out]) == 2
    assert "no run logs metric 'nope'" in capsys.readouterr().err


def test_summary_names_each_seed_final_against_its_own_best():
    from lnnmpc.train.report import eval_table, seed_finals

    returns = {(100, 0): [500.0, 520.0], (100, 1): [800.0, 810.0], (200, 0): [700.0, 700.0], (200, 1): [300.0, 310.0]}
    rows = [{"env_step": str(step), "seed": str(seed), "episode": str(i), "return": str(value)}
            for (step, seed), values in returns.items() for i, value in enumerate(values)]
    table = eval_table(rows)
    assert [t["per_seed"] for t in table] == [{0: 510.0, 1: 805.0}, {0: 700.0, 1: 305.0}]
    assert seed_finals(table) == ("Per seed at the last evaluation: seed 0 700.0 (its best 700.0 at 200), "
                                  "seed 1 305.0 (its best 805.0 at 100).")
    assert seed_finals(eval_table([r for r in rows if r["seed"] == "0"])) is None  # one seed: the mean says it
    assert seed_finals([]) is None


def test_tables_give_each_run_per_evaluation_stats_and_speed(tmp_path, capsys):
    from lnnmpc.train.tables import main as tables_main

    a = _run(tmp_path / "a", "tdmpc2", {10: [[100.0, 300.0], [500.0, 700.0]], 20: [[800.0, 800.0], [600.0, 600.0]],
                                         30: [[900.0, 910.0], [700.0, 690.0]]}, seeds=2)
    b = _run(tmp_path / "b", "cfc-zp-det", {20: [[50.0]]})
    timing = [{"env_step": 0, "phase": "compile", "seconds": 100.0, "env_steps_per_seed": 0,
               "env_steps_per_s_all_seeds": 0.0}]
    timing += [{"env_step": 10 * k, "phase": "train_chunk", "seconds": s, "env_steps_per_seed": 10,
                "env_steps_per_s_all_seeds": r} for k, s, r in ((1, 5.0, 400.0), (2, 6.0, 300.0), (3, 7.0, 200.0))]
    timing += [{"env_step": 30, "phase": "evaluate", "seconds": 3.5, "env_steps_per_seed": 0,
                "env_steps_per_s_all_seeds": 0.0}]
    runfolder.write_csv(os.path.join(a, "timing.csv"), list(timing[0]), timing)
    assert tables_main([a, b, "--labels", "A", "B", "--returns-only"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| env steps | A: mean ± std | A: over seeds | A: seeds | B: mean ± std")
    # step 10: episodes 100, 300, 500, 700 (std 223.6), seed means 200 / 600 (std 200); B has no evaluation there
    assert lines[2] == "| 10 | 400.0 ± 223.6 | 200.0 | 200 / 600 |  |  |  |"
    # B ran one seed: no spread over seeds to give (empty, not 0.0)
    assert lines[3] == "| 20 | 700.0 ± 100.0 | 100.0 | 800 / 600 | 50.0 ± 0.0 |  | 50 |"
    assert lines[-1] == "| mean of the last 3 | 633.3 |  |  |  |  |  |"  # (400 + 700 + 800) / 3; B has one
    # Each run's last evaluation split at a return: A's step 30 has 690 under 695; all of B's one episode is under.
    assert tables_main([a, b, "--labels", "A", "B", "--returns-only", "--falls-below", "695"]) == 0
    falls = capsys.readouterr().out.split("\n\n")[1].splitlines()
    assert falls[0] == ("| run | env steps | episodes | under 695 | under 695, last 3 evaluations | mean | "
                        "mean of the others | best | worst |")
    # over A's last 3 evaluations 100, 300, 500, 600, 600 and 690 are under 695: 6 of 12 episodes
    assert falls[2:] == ["| A | 30 | 4 | 1 | 6 of 12 | 800.0 | 836.7 | 910.0 | 690.0 |",
                         "| B | 20 | 1 | 1 | 1 of 1 | 50.0 |  | 50.0 | 50.0 |"]
    with pytest.raises(SystemExit):
        tables_main([a, "--falls-below", "nan"])
    assert "--falls-below needs a finite return, got nan" in capsys.readouterr().err
    assert tables_main([a, "--labels", "A", "--speed-only"]) == 0
    row = capsys.readouterr().out.splitlines()[-1]
    # median chunk 300 env steps/s over 2 seeds; everything logged 100 + 18 + 3.5 s
    assert row == "| A |  | 100.0 | 18.0 (3 × 10 steps) | 300 | 150 | 3.5 (1) | 122 |"  # no startup row: older runs
    startup = {"env_step": 0, "phase": "startup", "seconds": 12.5, "env_steps_per_seed": 0,
               "env_steps_per_s_all_seeds": 0.0}
    runfolder.write_csv(os.path.join(a, "timing.csv"), list(timing[0]), [startup, *timing])
    assert tables_main([a, "--labels", "A", "--speed-only"]) == 0
    row = capsys.readouterr().out.splitlines()[-1]
    assert row == "| A | 12.5 | 100.0 | 18.0 (3 × 10 steps) | 300 | 150 | 3.5 (1) | 134 |"  # "all" counts it
    assert tables_main([b, "--speed-only"]) == 2
    assert "has no timing.csv" in capsys.readouterr().err
    with open(os.path.join(a, "config.json")) as f:  # a provenance entry as the trainer writes it
        config = json.load(f)
    config["provenance"] = [{"command": "python -m lnnmpc.train.cli train --task cartpole-swingup"},
                            {"command": f"python -m lnnmpc.train.cli train --resume {a}"}]
    runfolder.write_text(os.path.join(a, "config.json"), json.dumps(config))
    assert tables_main([a, b, "--labels", "A", "B", "--commands-only"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "```bash", "# A", "python -m lnnmpc.train.cli train --task cartpole-swingup",  # the first start's
        "# B", f"# ({b}: no command recorded)", "```"]
    assert tables_main([a, "--labels", "A"]) == 0  # all three by default
    out = capsys.readouterr().out
    assert out.startswith("| env steps | A: mean") and "| run | startup s | compile s |" in out
    assert out.rstrip().endswith("```")


def test_tables_pool_runs_of_one_configuration_into_one_column(tmp_path, capsys):
    from lnnmpc.train.tables import main as tables_main

    # a 2-seed run with master seed 0 and a 1-seed run with master seed 5: one configuration, three seeds
    a = _run(tmp_path / "a", "tdmpc2", {10: [[100.0, 300.0], [500.0, 700.0]], 20: [[800.0], [600.0]]}, seeds=2)
    b = _run(tmp_path / "b", "tdmpc2", {10: [[0.0, 200.0]], 20: [[400.0]], 30: [[900.0]]}, seeds=1, seed=5)
    assert tables_main([a, b, "--labels", "A", "B", "--pool", "A+B", "--returns-only", "--falls-below", "500"]) == 0
    returns, falls = capsys.readouterr().out.split("\n\n")
    lines = returns.splitlines()
    assert lines[0].endswith("| A+B: mean ± std | A+B: over seeds | A+B: seeds |")
    # step 10: seed means 200 / 600 / 100 (the pooled column's seeds in run order), episodes' std over all six
    assert lines[2].endswith("| 300.0 ± 238.0 | 216.0 | 200 / 600 / 100 |")
    assert lines[3].endswith("| 600.0 ± 163.3 | 163.3 | 800 / 600 / 400 |")
    assert lines[4].endswith("| 900.0 ± 0.0 |  | 900 |  |  |  |")  # only b evaluated at 30: not pooled
    # over the pooled evaluations (10 and 20): 100, 300, 0, 200 and 400 are under 500
    assert falls.splitlines()[-1] == "| A+B | 20 | 3 | 1 | 5 of 9 | 600.0 | 700.0 | 800.0 | 400.0 |"
    # runs that differ in what they learn are refused, naming the setting; so is pooling one run
    c = _run(tmp_path / "c", "tdmpc2", {10: [[1.0]]}, seeds=1, batch_size=128)
    assert tables_main([a, c, "--pool", "x"]) == 2
    assert "differ in batch_size: 256 != 128" in capsys.readouterr().err
    noisy = _run(tmp_path / "noisy", "tdmpc2", {10: [[1.0]]}, seeds=1, obs={"noise": 0.1})  # a corruption set
    assert tables_main([a, noisy, "--pool", "x"]) == 2
    assert "differ in eval_obs: {} != {'obs_noise': 0.1}; obs: {} != {'obs_noise': 0.1}" in capsys.readouterr().err
    assert tables_main([a, "--pool", "x"]) == 2
    assert "--pool needs at least two run folders" in capsys.readouterr().err
    d = _run(tmp_path / "d", "tdmpc2", {40: [[1.0]]}, seeds=1)
    assert tables_main([a, d, "--pool", "x"]) == 2
    assert "share no evaluation step" in capsys.readouterr().err
    # runs joined by "+" are one pooled column of their own (default label: the pooled seed count); the per-run
    # tables list the pooled runs one by one
    assert tables_main([f"{a}+{b}", a, "--returns-only"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| env steps | tdmpc2 (3 seeds pooled): mean ± std |")
    assert lines[2].startswith("| 10 | 300.0 ± 238.0 | 216.0 | 200 / 600 / 100 | 400.0 ± 223.6 |")
    assert tables_main([f"{a}+{b}", "--labels", "AB", "--commands-only"]) == 0
    labels = [line for line in capsys.readouterr().out.splitlines() if line.startswith("# AB")]
    assert labels == ["# AB: a", "# AB: b"]
    assert tables_main([f"{a}+{c}"]) == 2
    assert "differ in batch_size: 256 != 128" in capsys.readouterr().err
    assert tables_main([f"{a}+{b}", a, "--pool", "x"]) == 2  # a's seeds would count twice
    assert "cannot pool a run with itself" in capsys.readouterr().err


def test_tables_read_an_eval_commands_csv_in_place_of_the_trainings(tmp_path, capsys):
    from lnnmpc.train.tables import main as tables_main

    # two one-seed runs whose final policies were evaluated again with more episodes (`cli eval` writes evals/*.csv,
    # with the backend and corruption columns); the training's own eval.csv must not be read
    a = _run(tmp_path / "a", "tdmpc2", {20: [[1.0]]}, seeds=1)
    b = _run(tmp_path / "b", "tdmpc2", {20: [[2.0]]}, seeds=1, seed=5)
    fields = ["env_step", "seed", "episode", "return", "backend", "obs"]
    for run, returns in ((a, [700.0, 760.0, 10.0, 790.0]), (b, [750.0, 770.0])):
        rows = [{"env_step": 20, "seed": 0, "episode": e, "return": r, "backend": "dm_control", "obs": "clean"}
                for e, r in enumerate(returns)]
        os.makedirs(os.path.join(run, "evals"))
        runfolder.write_csv(os.path.join(run, "evals", "dm_control-clean-20.csv"), fields, rows)
    assert tables_main([f"{a}+{b}", "--labels", "AB", "--evals", "dm_control-clean-20.csv", "--returns-only",
                        "--falls-below", "400"]) == 0
    returns, falls = capsys.readouterr().out.split("\n\n")
    # six episodes (mean 630, std 278.6 over all); seed means 565 (a) and 760 (b), their std 97.5
    assert returns.splitlines()[2] == "| 20 | 630.0 ± 278.6 | 97.5 | 565 / 760 |"
    # one of six under 400; the other five average 754
    assert falls.splitlines()[-1] == "| AB | 20 | 6 | 1 | 1 of 6 | 630.0 | 754.0 | 790.0 | 10.0 |"
    # a name the runs do not hold is refused, naming what evals/ holds
    assert tables_main([a, "--evals", "mjx-clean-20.csv"]) == 2
    assert "no evaluation rows in evals/mjx-clean-20.csv; its evals/ holds dm_control-clean-20.csv" in \
        capsys.readouterr().err
    c = _run(tmp_path / "c", "tdmpc2", {20: [[1.0]]}, seeds=1)
    assert tables_main([c, "--evals", "dm_control-clean-20.csv"]) == 2
    assert "its evals/ holds no CSV (write one with `cli eval`)" in capsys.readouterr().err


def test_reports_without_plots_rewrite_only_the_summary(tmp_path):
    from lnnmpc.train import report

    a = _run(tmp_path / "a", "tdmpc2", {10000: [[100.0, 300.0]], 20000: [[600.0, 700.0]]})
    rows = [{"env_step": 1000 * k, "seed": 0, "episode_return": 10.0 * k, "total_loss": 1.0 / k} for k in (1, 2, 3)]
    runfolder.write_csv(os.path.join(a, "train.csv"), list(rows[0]), rows)
    report.write_reports(a, {"env_steps": 20000, "train_seconds": 60.0})
    figures = [os.path.join(a, name) for name in ("curve.png", "training.png")]
    assert all(os.path.getsize(f) > 5_000 for f in figures)  # palette PNGs of a few points
    assert "Training time (this machine, incl. compilation): 1.0 min." in open(os.path.join(a, "summary.md")).read()
    for f in figures:
        os.remove(f)
    report.write_reports(a, {"env_steps": 20000, "train_seconds": 120.0}, plots=False)  # the trainer's last call
    assert not any(os.path.exists(f) for f in figures)
    summary = open(os.path.join(a, "summary.md")).read()
    assert "1.0 min." not in summary and "Training time (this machine, incl. compilation): 2.0 min." in summary
    assert "**Final return 650.0" in summary


def test_compare_plots_the_policy_priors_returns_of_runs_that_log_them(tmp_path, capsys):
    """``--eval-column prior_return``: the curve of the prior's returns (evaluations before a resumed run turned
    eval_prior on have none and are left out); a run without the column is refused, naming the columns it has.
    The run's own summary gives the prior's last evaluation beside MPPI's."""
    from lnnmpc.train import report

    a = _run(tmp_path / "a", "tdmpc2", {10000: [[100, 300]], 20000: [[600, 700]]}, eval_prior=True)
    rows = runfolder.read_csv(os.path.join(a, "eval.csv"))
    for r, prior in zip(rows, ["", "", "50", "150"], strict=True):
        r["prior_return"] = prior
    runfolder.write_csv(os.path.join(a, "eval.csv"), list(rows[0]), rows)
    out = str(tmp_path / "prior.png")
    assert main([a, "--eval-column", "prior_return", "--out", out]) == 0
    with open(str(tmp_path / "prior.csv")) as f:
        assert [(r["column"], r["env_step"], float(r["mean"])) for r in csv.DictReader(f)] == [
            ("prior_return", "20000", 100.0)]
    assert main([a, "--out", out]) == 0  # MPPI's returns, as before
    with open(str(tmp_path / "prior.csv")) as f:
        assert [(r["column"], r["env_step"], float(r["mean"])) for r in csv.DictReader(f)] == [
            ("return", "10000", 200.0), ("return", "20000", 650.0)]
    b = _run(tmp_path / "b", "tdmpc2", {10000: [[1.0]]})
    assert main([a, b, "--eval-column", "prior_return", "--out", out]) == 2
    assert f"{b!r} logs no 'prior_return' in eval.csv; its columns: env_step, seed, episode, return" in (
        capsys.readouterr().err)
    from lnnmpc.train.tables import main as tables_main

    assert tables_main([a, "--labels", "A", "--returns-only", "--eval-column", "prior_return"]) == 0
    table = capsys.readouterr().out
    assert "| 20,000 | 100.0 ± 50.0 |" in table and "10,000" not in table and "650.0" not in table
    assert tables_main([a, b, "--returns-only", "--eval-column", "prior_return"]) == 2
    assert f"{b!r} logs no 'prior_return'" in capsys.readouterr().err
    for run in (a, b):
        report.write_reports(run)  # curve.png: a dashed curve of the prior where the run logs it
        assert os.path.getsize(os.path.join(run, "curve.png")) > 10_000
    summary = open(os.path.join(a, "summary.md")).read()
    assert "**Final return 650.0" in summary
    assert "The policy prior alone on the same episodes: 100.0 ± 50.0 at 20,000 env steps (best 100.0)." in summary
    assert "policy prior" not in open(os.path.join(b, "summary.md")).read()
