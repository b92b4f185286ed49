"""Aggregation of study runs (lnnmpc.experiments.aggregate), the thesis's values and the study figures, on fake run
folders, against sums computed by hand."""

import csv
import os

import numpy as np
import pytest
from run_folders import fake_run, write_rows

from lnnmpc.experiments import grid, run
from lnnmpc.experiments.aggregate import markdown, newest_eval, read_returns, study_rows, summarize
from lnnmpc.experiments.thesis import tdmpc2_value, thesis_value


def test_summarize_against_hand_computation():
    returns = np.array([[100.0, 200.0, 300.0], [400.0, 500.0, 600.0]])
    s = summarize(returns)
    assert s["mean"] == pytest.approx(350.0)
    assert s["std"] == pytest.approx(np.sqrt(np.mean((returns - 350.0) ** 2)))
    assert s["std_seeds"] == pytest.approx(150.0)
    assert (s["seeds"], s["episodes"]) == (2, 3)
    with pytest.raises(ValueError, match="shape"):
        summarize(np.zeros(3))


def test_thesis_values():
    assert thesis_value("cartpole-swingup", "remove_vel=1", "cfc-zp-det").std is None
    ref = thesis_value("cartpole-swingup", "flicker=0.2,noise=0.3", "ltc-op-stoch")
    assert (ref.mean, ref.std, ref.source) == (721.52, 78.38, "Table 5.4")
    assert tdmpc2_value("acrobot-swingup", "").mean == 329.0
    assert thesis_value("walker-run", "delay=2", "tdmpc2") is None


def test_aggregation_and_markdown(tmp_path):
    options = grid.GridOptions(runs_dir=str(tmp_path), steps=200_000, seeds=2, agents=("tdmpc2", "cfc-op-det"))
    study = grid.get_study("table5_4")
    specs = grid.expand(study, options)
    noisy = specs[2].folder  # tdmpc2 on noise0.1-flicker0.2
    fake_run(noisy, 200_016, returns=[[300.0, 400.0], [500.0, 600.0]],
             eval_name="mjx-flicker0.2-noise0.2-200016.csv")
    write_rows(os.path.join(noisy, "evals", "mjx-flicker0.2-noise0.2-100000.csv"),
               [{"env_step": 100_000, "seed": 0, "episode": 0, "return": 1.0}])
    assert newest_eval(noisy, "noise=0.2,flicker=0.2", "mjx", None).endswith("-200016.csv")
    rows = study_rows(study, specs, options.steps)
    assert len(rows) == 2 + 2 * 3
    row = next(r for r in rows if r["run"] == noisy and r["eval_obs"] == "flicker0.2-noise0.2")
    assert (row["env_step"], row["seeds"], row["episodes"], row["mean"]) == (200_016, 2, 2, 450.0)
    assert row["std"] == pytest.approx(np.std([300, 400, 500, 600]))
    assert row["std_seeds"] == pytest.approx(100.0)
    assert (row["thesis_mean"], row["thesis_std"], row["tdmpc2_mean"]) == (353.63, 76.27, 353.63)
    assert row["status"] == "finished"
    text = markdown(study, rows)
    assert "| cartpole-swingup | flicker0.2-noise0.1 | flicker0.2-noise0.2 | tdmpc2 | 200,016 | 2 × 2 | 450.0 ± " \
           "111.8 | 100.0 | 353.6 ± 76.3 | 353.6 ± 76.3 |" in text
    assert text.count("not yet run") == 7
    assert "| novel | novel | cfc-op-det | not yet run |  |  |  | 868.3 ± 2.1 | 193.2 ± 13.7 |" in text
    paths = run.aggregate("table5_4", specs, options, str(tmp_path / "out"))
    with open(paths[0], newline="") as f:
        assert len(list(csv.DictReader(f))) == 8


def test_horizon_rows_carry_planner_time(tmp_path):
    options = grid.GridOptions(runs_dir=str(tmp_path), seeds=1)
    study = grid.get_study("fig5_19")
    specs = grid.expand(study, options)
    folder = specs[0].folder
    write_rows(os.path.join(folder, "evals", "horizon3-clean-200016.csv"),
               [{"env_step": 200_016, "seed": 0, "episode": e, "return": 100.0 * e, "planner_ms": ms}
                for e, ms in enumerate((2.0, 3.0, 10.0))])
    step, returns, timing = read_returns(os.path.join(folder, "evals", "horizon3-clean-200016.csv"))
    assert step == 200_016 and returns.shape == (1, 3) and timing.tolist() == [2.0, 3.0, 10.0]
    rows = study_rows(study, specs, options.steps)
    assert [r["horizon"] for r in rows] == [1, 3, 5, 10, 16]
    assert rows[1]["planner_ms"] == 3.0 and rows[1]["mean"] == 100.0 and rows[0]["mean"] == ""
    assert "| acrobot-swingup | clean | clean | cfc-zp-det | 3 | 200,016 | 1 × 3 | 100.0 ± 81.6 | 0.0 | 3.0 ± " \
           in markdown(study, rows)


def test_table_rows_take_the_evaluation_at_the_trained_planning_horizon(tmp_path):
    """Figure 5.19 trains Table 5.3's acrobot cfc-zp-det run and evaluates it per horizon only: the table reads
    the horizon file at the run's own H_plan (10 here), not another horizon's, and a newer plain file wins."""
    options = grid.GridOptions(runs_dir=str(tmp_path), seeds=1, agents=("cfc-zp-det",))
    study = grid.get_study("table5_3")
    spec = next(s for s in grid.expand(study, options) if s.condition.task == "acrobot-swingup")
    folder = spec.folder
    fake_run(folder, 164_688, returns=[[700.0, 900.0]], eval_name="horizon10-clean-164688.csv")
    write_rows(os.path.join(folder, "evals", "horizon3-clean-184688.csv"),
               [{"env_step": 184_688, "seed": 0, "episode": 0, "return": 1.0}])
    row = next(r for r in study_rows(study, [spec], options.steps) if r["task"] == "acrobot-swingup")
    assert row["mean"] == ""  # the run does not say which horizon it was trained with
    with open(os.path.join(folder, "config.json"), "w") as f:
        f.write('{"config": {}, "agent_config": {"planner": {"horizon": 10}}}')
    row = study_rows(study, [spec], options.steps)[0]
    assert (row["env_step"], row["mean"], row["status"]) == (164_688, 800.0, "partial")
    write_rows(os.path.join(folder, "evals", "mjx-clean-164688.csv"),
               [{"env_step": 164_688, "seed": 0, "episode": 0, "return": 5.0}])
    assert study_rows(study, [spec], options.steps)[0]["mean"] == 5.0  # a tie: the plain file
    write_rows(os.path.join(folder, "evals", "mjx-clean-184688.csv"),
               [{"env_step": 184_688, "seed": 0, "episode": 0, "return": 6.0}])
    assert study_rows(study, [spec], options.steps)[0]["env_step"] == 184_688
    assert study_rows(study, [spec], options.steps, backend="dm_control")[0]["mean"] == ""


def _fake_noise_evals(folder, step, means):
    """Evaluation files of a run at σ = 0.1, 0.2, 0.3 (2 seeds × 2 episodes, returns mean ± 10)."""
    for sigma, mean in zip((0.1, 0.2, 0.3), means, strict=True):
        write_rows(os.path.join(folder, "evals", f"mjx-noise{sigma:g}-{step}.csv"),
                   [{"env_step": step, "seed": s, "episode": e, "return": mean + (10.0 if e else -10.0)}
                    for s in range(2) for e in range(2)])


def test_study_figure_series_and_png(tmp_path):
    """Table 5.5's figure: ours against σ for the measured agents beside the thesis's; nothing measured, no
    figure; a partial run's step is in its label."""
    import matplotlib.image

    from lnnmpc.experiments import figures

    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, seeds=2)
    specs = grid.expand(grid.get_study("table5_5"), options)
    study, out = grid.get_study("table5_5"), str(tmp_path / "fig.png")
    rows = study_rows(study, specs, options.steps)
    assert figures.write_study_figure(study, specs, rows, out, options.steps) is None and not os.path.exists(out)
    fake_run(specs[1].folder, 40_000)  # cfc-zp-det, stopped at 40K
    _fake_noise_evals(specs[1].folder, 40_000, (300.0, 200.0, 100.0))
    rows = study_rows(study, specs, options.steps)
    series = figures.sweep_series(rows)[("acrobot-swingup", "noise0.1")]
    assert list(series) == list(study.agents)
    cfc = series["cfc-zp-det"]
    assert cfc["sigma"] == [0.1, 0.2, 0.3] and cfc["mean"] == [300.0, 200.0, 100.0] and cfc["std"] == [10.0] * 3
    assert cfc["thesis"] == [thesis_value("acrobot-swingup", f"noise={s}", "cfc-zp-det").mean for s in (0.1, 0.2, 0.3)]
    assert cfc["env_step"] == 40_000 and series["tdmpc2"]["env_step"] is None
    assert np.isnan(series["tdmpc2"]["mean"]).all()
    assert figures.bar_series(rows) == ([], {})  # every condition of Table 5.5 is a noise sweep
    assert figures._steps_label(40_000, 50_000) == " (40K)" and figures._steps_label(50_016, 50_000) == ""
    assert figures.write_study_figure(study, specs, rows, out, options.steps) == out
    image = matplotlib.image.imread(out)
    assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 600
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_bar_series_of_single_setting_conditions(tmp_path):
    from lnnmpc.experiments import figures

    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, agents=("tdmpc2",))
    specs = grid.expand(grid.get_study("table5_4"), options)  # remove_vel (one setting) and the noise sweep
    fake_run(specs[0].folder, 50_016, returns=[[190.0, 210.0]], eval_name="mjx-novel-50016.csv")
    conditions, series = figures.bar_series(study_rows(grid.get_study("table5_4"), specs, options.steps))
    assert conditions == [("cartpole-swingup", "novel")]
    assert series == {"tdmpc2": {"mean": [200.0], "std": [10.0], "thesis": [193.22], "env_step": [50_016]}}


def test_horizon_figure_reads_every_episode(tmp_path):
    from lnnmpc.experiments import figures

    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, seeds=1)
    specs = grid.expand(grid.get_study("fig5_19"), options)
    fake_run(specs[0].folder, 50_016)
    for h in (1, 10):
        write_rows(grid.eval_file(specs[0].folder, 50_016, "", horizon=h),
                   [{"env_step": 50_016, "seed": 0, "episode": e, "return": 100.0 * h + e, "horizon": h,
                     "planner_ms": 2.0 * h + e} for e in range(3)])
    samples = figures.horizon_samples(specs)
    assert list(samples) == [1, 10]
    np.testing.assert_array_equal(samples[10][0], [1000.0, 1001.0, 1002.0])
    np.testing.assert_array_equal(samples[1][1], [2.0, 3.0, 4.0])
    assert samples[1][2] == 50_016
    paths = run.aggregate("fig5_19", specs, options, str(tmp_path / "out"))
    assert [os.path.basename(p) for p in paths] == ["fig5_19.csv", "fig5_19.md", "fig5_19.png"]
    assert os.path.getsize(paths[2]) > 10_000
