"""``python -m lnnmpc.train.paired``: evaluations of several policies on the same episodes, compared row by row."""

from __future__ import annotations

import json
import os
import subprocess

import pytest

from lnnmpc.train import runfolder
from lnnmpc.train.paired import (
    check_same_training_episodes,
    evaluation_at,
    main,
    paired_rows,
    read_training_evaluations,
    training_evaluations_by_number,
)

FIELDS = ["env_step", "seed", "episode", "return", "backend", "obs", "actor", "planner", "eval_seed"]


def _csv(path, returns, *, seeds=1, backend="mjx", eval_seed=0, step=200, reverse=False, fields=FIELDS):
    """A ``cli eval`` CSV: ``returns`` in (seed, episode) order, written in reverse row order with ``reverse``."""
    episodes = len(returns) // seeds
    rows = [{"env_step": step, "seed": i // episodes, "episode": i % episodes, "return": r, "backend": backend,
             "obs": "clean", "actor": "planner", "planner": "", "eval_seed": eval_seed}
            for i, r in enumerate(returns)]
    runfolder.write_csv(str(path), fields, [{k: row[k] for k in fields} for row in (rows[::-1] if reverse else rows)])
    return str(path)


def test_paired_differences_against_a_hand_computation(tmp_path, capsys):
    """A = 10, 20, 30, 40 and B = 12, 19, 35, 44 on the same 2 seeds x 2 episodes, B's rows in reverse order:
    differences 2, -1, 5, 4, so +2.5 with standard error sqrt(7) / 2 = 1.32, 3 more and 1 less; correlation
    560 / sqrt(500 x 641) = 0.989; A's mean 25.0 ± sqrt(125) = 11.2."""
    a = _csv(tmp_path / "a.csv", [10, 20, 30, 40], seeds=2)
    b = _csv(tmp_path / "b.csv", [12, 19, 35, 44], seeds=2, reverse=True)
    plot = tmp_path / "fig" / "paired.png"
    assert main([a, b, "--labels", "A", "B", "--plot", str(plot)]) == 0
    out, err = capsys.readouterr()
    assert "not the spread between training launches" in err  # the standard error counts the starts alone
    assert "| A | 4 | 25.0 ± 11.2 |  |  |  |" in out
    assert "| B | 4 | 27.5 ± 12.7 | +2.5 ± 1.3 | 3 / 1 | 0.99 |" in out
    assert "minus A (± standard error)" in out and os.path.getsize(plot) > 10_000


def test_paired_refuses_csvs_of_other_episodes_naming_why(tmp_path, capsys):
    a = _csv(tmp_path / "a.csv", [1, 2, 3])
    cases = [
        (_csv(tmp_path / "seed1.csv", [1, 2, 3], eval_seed=1), "eval_seed '1' against '0'"),
        (_csv(tmp_path / "dmc.csv", [1, 2, 3], backend="dm_control"), "backend 'dm_control' against 'mjx'"),
        (_csv(tmp_path / "two.csv", [1, 2]), "only in the first [(0, 2)], only in 'two.csv' none"),
    ]
    train = tmp_path / "eval.csv"
    runfolder.write_csv(str(train), ["env_step", "seed", "episode", "return"],
                        [{"env_step": 10, "seed": 0, "episode": e, "return": 1.0} for e in range(3)])
    cases.append((str(train), "is not a CSV of `cli eval` (no backend, obs column"))
    both = tmp_path / "both.csv"
    runfolder.write_csv(str(both), FIELDS, [{**r, "env_step": s} for s in (10, 20) for r in runfolder.read_csv(a)])
    cases.append((str(both), "holds evaluations of several checkpoints (10, 20): one per CSV"))
    for other, reason in cases:
        assert main([a, other]) == 2
        assert reason in capsys.readouterr().err, other
    assert main([a]) == 2 and "give at least two CSVs to compare, got 1" in capsys.readouterr().err
    assert main([a, a, "--labels", "only"]) == 2
    assert "1 labels for 2 CSVs: give one label per CSV" in capsys.readouterr().err
    assert main([a, str(tmp_path / "missing.csv")]) == 2
    assert "no evaluation CSV at" in capsys.readouterr().err


def test_common_compares_the_rows_both_hold_and_old_csvs_are_noted(tmp_path, capsys):
    """An evaluation of 2 episodes against one of 4 with the same seed (its first 2 episodes are the same ones):
    refused as it is, compared over the 2 shared rows with --common. A CSV written before eval_seed was recorded
    passes with a note."""
    long = _csv(tmp_path / "long.csv", [100, 200, 300, 400])
    short = _csv(tmp_path / "short.csv", [110, 190], fields=FIELDS[:-1])
    assert main([long, short]) == 2
    assert "compare the rows they share with --common" in capsys.readouterr().err
    assert main([long, short, "--common", "--labels", "20", "10"]) == 0
    out, err = capsys.readouterr()
    assert "| 20 | 2 | 150.0 ± 50.0 |  |  |  |" in out  # 100 and 200
    assert "| 10 | 2 | 150.0 ± 40.0 | +0.0 ± 10.0 | 1 / 1 | 1.00 |" in out  # 110 and 190: +10 and -10
    assert f"note: {short!r} records no eval_seed" in err
    apart = _csv(tmp_path / "apart.csv", [5], seeds=1, reverse=False, step=200)
    runfolder.write_csv(apart, FIELDS, [{**runfolder.read_csv(apart)[0], "seed": 3}])
    assert main([long, apart, "--common"]) == 2 and "share no (seed, episode) row" in capsys.readouterr().err


def _run(path, evaluations, *, seeds=2, seed=1, time="2026-12-01T00:00:00Z", **config):
    """A run folder: config.json (what decides its evaluations' episodes, one provenance entry started at
    ``time``) and eval.csv, ``evaluations`` mapping each env step to its returns in (seed, episode) order."""
    path.mkdir(parents=True)
    settings = {"task": "acrobot-swingup", "seed": seed, "seeds": seeds, "eval_episodes": 2, "eval_obs": {},
                "physics": "fast", **config}
    (path / "config.json").write_text(json.dumps({"config": settings, "provenance": [{"time": time}]}))
    rows = [{"env_step": step, "seed": i // 2, "episode": i % 2, "return": r}
            for step, returns in evaluations.items() for i, r in enumerate(returns)]
    runfolder.write_csv(str(path / "eval.csv"), ["env_step", "seed", "episode", "return"], rows)
    return str(path)


def test_runs_are_paired_on_the_training_evaluation_they_share(tmp_path, capsys):
    """Runs of one master seed differing in other settings (the rate, the action repeat) play the same episodes at
    their k-th evaluation: the last step both evaluated at by default (20: the returns of the hand computation
    above give its numbers again), --step for an earlier one (10: differences 0, 1, -1, 0, so +0.0 with standard
    error sqrt(2/3) / 2 = 0.41; correlation 4 / 5 = 0.80)."""
    a = _run(tmp_path / "a", {10: [1, 2, 3, 4], 20: [10, 20, 30, 40]}, action_repeat=4)
    b = _run(tmp_path / "b", {10: [1, 3, 2, 4], 20: [12, 19, 35, 44], 30: [0, 0, 0, 0]}, action_repeat=8, lr=6e-4)
    assert main(["--runs", a, b]) == 0
    out = capsys.readouterr().out
    assert "| a | 4 | 25.0 ± 11.2 |  |  |  |" in out and "| b | 4 | 27.5 ± 12.7 | +2.5 ± 1.3 | 3 / 1 | 0.99 |" in out
    assert main(["--runs", a, b + "/", "--step", "10", "--labels", "recipe", "lr"]) == 0
    assert "| lr | 4 | 2.5 ± 1.1 | +0.0 ± 0.4 | 1 / 1 | 0.80 |" in capsys.readouterr().out
    assert main(["--runs", a, b, "--step", "all"]) == 0  # one table per shared step, in order (not 30: a lacks it)
    sections = capsys.readouterr().out.split("env step ")[1:]
    assert [x.split("\n")[0] for x in sections] == ["10", "20"]
    assert "| b | 4 | 2.5 ± 1.1 | +0.0 ± 0.4 | 1 / 1 | 0.80 |" in sections[0]
    assert "| b | 4 | 27.5 ± 12.7 | +2.5 ± 1.3 | 3 / 1 | 0.99 |" in sections[1]
    one = _run(tmp_path / "one", {20: [10, 20, 30, 40]}, seeds=2)
    late = _run(tmp_path / "late", {20: [12, 19, 35, 44]}, seeds=2)
    assert main(["--runs", one, late, "--step", "all"]) == 0  # a single shared step still names itself
    assert capsys.readouterr().out.startswith("env step 20\n\n| policy |")


def test_runs_evaluated_at_other_steps_pair_by_their_kth_evaluation(tmp_path, capsys):
    """Another action repeat moves every evaluation to another step (acrobot: 200,128 against 200,256); the k-th
    evaluations still played the same episodes, so --evaluation K pairs them (the numbers of the test above)."""
    a = _run(tmp_path / "a", {10: [1, 2, 3, 4], 20: [10, 20, 30, 40]}, action_repeat=4)
    b = _run(tmp_path / "b", {12: [1, 3, 2, 4], 24: [12, 19, 35, 44]}, action_repeat=6)
    assert main(["--runs", a, b]) == 2 and "pair by their k-th evaluation: --evaluation K" in capsys.readouterr().err
    assert main(["--runs", a, b, "--evaluation", "-1"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("evaluation -1 of each run, at env step 20 / 24\n\n| policy |")
    assert "| b | 4 | 27.5 ± 12.7 | +2.5 ± 1.3 | 3 / 1 | 0.99 |" in out
    assert main(["--runs", a, b, "--evaluation", "1"]) == 0
    assert "| b | 4 | 2.5 ± 1.1 | +0.0 ± 0.4 | 1 / 1 | 0.80 |" in capsys.readouterr().out
    longer = _run(tmp_path / "longer", {12: [0] * 4, 24: [0] * 4, 36: [0] * 4})
    assert main(["--runs", a, longer, "--evaluation", "-1"]) == 2  # a's second evaluation against its third
    assert "evaluation number (0: the first) 2 against 1" in capsys.readouterr().err
    for argv, reason in [
        (["--runs", longer, b, "--evaluation", "3"], f"{b!r} holds 2 evaluation(s): --evaluation 3 picks none"),
        (["--runs", a, b, "--evaluation", "0"], "--evaluation counts from 1 (the first) or from -1 (the last), got 0"),
        ([a, b, "--evaluation", "1"], "--evaluation picks a training evaluation: give it with --runs"),
        (["--runs", a, b, "--evaluation", "1", "--step", "10"], "give --step (an env step every run evaluated at)"),
    ]:
        assert main(argv) == 2
        assert reason in capsys.readouterr().err, argv


def test_runs_of_other_episodes_are_refused_naming_why(tmp_path, capsys):
    a = _run(tmp_path / "a", {10: [1, 2, 3, 4], 20: [5, 6, 7, 8]})
    cases = [
        (_run(tmp_path / "seed2", {20: [5, 6, 7, 8]}, seed=2), "master seed (--seed) 2 against 1"),
        (_run(tmp_path / "late", {20: [5, 6, 7, 8]}), "evaluation number (0: the first) 0 against 1"),
        (_run(tmp_path / "task", {10: [1] * 4, 20: [1] * 4}, task="cartpole-swingup"),
         'task "cartpole-swingup" against "acrobot-swingup"'),
        (_run(tmp_path / "old", {10: [1] * 4, 20: [1] * 4}, time="2026-11-28T00:00:00Z"),
         "drew their starts before 45dda0c"),
        (_run(tmp_path / "none", {30: [1] * 4}), "the runs share no evaluation step"),
        (str(tmp_path / "missing"), "is not a run folder"),
    ]
    for other, reason in cases:
        assert main(["--runs", a, other]) == 2
        assert reason in capsys.readouterr().err, other
    assert main(["--runs", a, a, "--step", "15"]) == 2 and "evaluated at 10, 20, not at 15" in capsys.readouterr().err
    assert main([a, a, "--step", "10"]) == 2 and "give it with --runs" in capsys.readouterr().err
    assert main(["--runs", a, a, "--step", "all", "--plot", str(tmp_path / "p.png")]) == 2
    assert "--plot draws one evaluation's episodes: give --step STEP, not all" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--runs", a, a, "--step", "last"])
    assert "an env step or 'all', got 'last'" in capsys.readouterr().err


def test_the_committed_constant_rate_run_pairs_with_the_recipe():
    """RESULTS.md [89]: master seed 1's recipe and its constant-rate line tie at 161,088 (+7.0 ± 44.6, 5 of 10)."""
    recipe = "experiments/results/cfc-acrobot-recipe-ar4-ar8-h100-200k/acrobot-recipe-ar4-seed1"
    constant = "experiments/results/cfc-acrobot-recipe-constlr-h100-200k/acrobot-recipe-constlr-seed1"
    root = os.path.join(os.path.dirname(__file__), "..")
    runs = [os.path.join(root, r) for r in (recipe, constant)]
    first, other = (evaluation_at(run, read_training_evaluations(run), 161_088) for run in runs)
    check_same_training_episodes(first, other)
    row = paired_rows([first, other], ["recipe", "constant"])[1]
    assert (round(row["diff"], 1), round(row["se"], 1), row["wins"], row["losses"]) == (7.0, 44.6, 5, 5)


def test_the_committed_action_repeat_runs_pair_by_their_last_evaluation():
    """RESULTS.md [93]: acting every 6 evaluates at 200,256, every 4 at 200,128; their fifth evaluations played the
    same starts (correlation 0.96 on master seed 1): -31.3 ± 15.8, more on 2 of 10."""
    root = os.path.join(os.path.dirname(__file__), "..", "experiments", "results")
    runs = [os.path.join(root, "cfc-acrobot-recipe-ar4-ar8-h100-200k", "acrobot-recipe-ar4-seed1"),
            os.path.join(root, "cfc-acrobot-recipe-ar6-h100-200k", "acrobot-recipe-ar6-seed1")]
    first, other = training_evaluations_by_number(runs, -1)
    assert (first.env_step, other.env_step) == (200_128, 200_256)
    row = paired_rows([first, other], ["every 4", "every 6"])[1]
    assert (round(row["diff"], 1), round(row["se"], 1), row["wins"], row["losses"]) == (-31.3, 15.8, 2, 8)


def test_make_paired_passes_the_evaluation_number():
    root = os.path.join(os.path.dirname(__file__), "..")
    result = subprocess.run(["make", "-n", "-s", "paired", "RUNS=runs/a runs/b", "EVALUATION=-1"], cwd=root,
                            capture_output=True, text=True, check=True)
    assert "lnnmpc.train.paired --runs runs/a runs/b --evaluation -1" in " ".join(
        result.stdout.replace("\\\n", " ").split())
