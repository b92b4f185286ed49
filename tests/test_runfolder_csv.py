"""train.csv grows columns after the seed phase (losses appear): the header must follow."""

import csv

from lnnmpc.train.runfolder import append_csv, truncate_csv


def test_append_csv_widens_the_header_when_rows_bring_new_columns(tmp_path):
    path = str(tmp_path / "train.csv")
    append_csv(path, [{"env_step": 2000, "seed": 0, "episode_return": 21.5}])
    append_csv(path, [{"env_step": 4000, "seed": 0, "episode_return": 30.0, "total_loss": 0.25}])
    append_csv(path, [{"env_step": 6000, "seed": 0, "episode_return": 45.0, "total_loss": 0.125}])
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert reader.fieldnames == ["env_step", "seed", "episode_return", "total_loss"]
    assert [r["total_loss"] for r in rows] == ["", "0.25", "0.125"]
    assert all(None not in r for r in rows)  # no value without a column
    truncate_csv(path, 4000)
    with open(path, newline="") as f:
        assert [r["env_step"] for r in csv.DictReader(f)] == ["2000", "4000"]


def test_training_plot_has_a_panel_per_logged_metric_and_a_line_per_seed(tmp_path):
    """train.csv as the trainer writes it: seed-phase rows without losses, then per-episode losses of 2 seeds."""
    from lnnmpc.train.report import plot_training, training_panels

    rows = [{"env_step": "1000", "seed": str(s), "episode_return": "5.0", "total_loss": "", "grad_norm": ""}
            for s in (0, 1)]
    rows += [{"env_step": str(step), "seed": str(s), "episode_return": str(step / 100 + s),
              "total_loss": str(1.0 / step), "grad_norm": str(0.5 + s)}
             for step in (2000, 3000, 4000) for s in (0, 1)]
    rows.append({"env_step": "5000", "seed": "1", "episode_return": "nan", "total_loss": "x", "grad_norm": "2"})
    panels = training_panels(rows)
    assert list(panels) == ["episode_return", "total_loss", "grad_norm"]
    steps, values = panels["episode_return"][1]
    assert steps.tolist() == [1000, 2000, 3000, 4000] and values.tolist() == [5.0, 21.0, 31.0, 41.0]
    assert panels["total_loss"][0][0].tolist() == [2000, 3000, 4000]  # blank seed-phase cells left out
    assert panels["grad_norm"][1][0].tolist() == [2000, 3000, 4000, 5000]
    assert training_panels([]) == {}
    evals = [{"env_step": str(step), "seed": str(s), "episode": str(e), "return": "1",
              "effective_rank": str(step / 1000 + e + s)} for step in (2000, 4000) for s in (0, 1) for e in (0, 1)]
    ranked = training_panels(rows, evals)
    assert list(ranked) == list(panels) + ["effective_rank (eval)"]
    steps, values = ranked["effective_rank (eval)"][1]
    assert steps.tolist() == [2000, 4000] and values.tolist() == [3.5, 5.5]  # mean over the episodes
    assert plot_training(str(tmp_path), rows, "cartpole-balance · tdmpc2", evals) == list(ranked)
    assert (tmp_path / "training.png").stat().st_size > 10_000


def test_progress_line_shows_a_dash_until_speed_and_return_are_measured():
    from lnnmpc.train.report import Progress

    progress = Progress(total=200_000)
    first = progress.line(4_992)
    assert "nan" not in first and first.endswith("— steps/s  last eval       —")
    assert first.startswith("[...") and "4,992/200,000 env steps" in first
    progress.rate, progress.last_eval = 151.4, 795.04
    assert progress.line(100_000).endswith("     151 steps/s  last eval   795.0")
    progress.last_prior = 412.26  # a run with eval_prior: the policy prior's mean beside MPPI's
    assert progress.line(100_000).endswith("     151 steps/s  last eval   795.0 (prior 412.3)")
    assert progress.line(100_000).startswith("[" + "#" * 15 + "." * 15 + "]")


def test_step_progress_estimates_the_time_left_and_redraws_at_most_once_a_second(capsys):
    from lnnmpc.train.report import StepProgress

    progress = StepProgress("agent steps")
    # 100 of 500 in 20 s: 400 more at the same pace take 80 s
    assert progress.line(100, 500, 20.0) == "[" + "#" * 6 + "." * 24 + "] 100/500 agent steps  20 s, ~80 s left"
    assert progress.line(500, 500, 95.0).endswith("500/500 agent steps  95 s, done")
    progress(1, 500)
    progress(2, 500)  # within the second: not drawn
    progress(500, 500)  # the end is always drawn, and ends the line
    err = capsys.readouterr().err
    assert err.count("\r") == 2 and "1/500 agent steps" in err and "2/500" not in err
    assert err.endswith("500/500 agent steps  0 s, done\n")
