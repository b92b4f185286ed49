"""``python -m lnnmpc.analysis.line_measures``: lines' final measures from run folders and ``cli eval`` CSVs."""

import csv

import pytest

from lnnmpc.analysis import line_measures


def _run(folder, evaluations):
    """A run folder whose eval.csv holds ``evaluations``: {env_step: {seed: [episode returns]}}."""
    folder.mkdir(parents=True)
    with open(folder / "eval.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["env_step", "seed", "episode", "return"])
        for step, seeds in evaluations.items():
            for seed, returns in seeds.items():
                writer.writerows([step, seed, e, r] for e, r in enumerate(returns))
    return str(folder)


def _eval_csv(path, returns, step=300, seeds=1):
    """A ``cli eval`` CSV of ``returns`` split evenly over ``seeds`` seeds."""
    per_seed = len(returns) // seeds
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["env_step", "seed", "episode", "return", "backend", "obs", "eval_seed"])
        for i, r in enumerate(returns):
            writer.writerow([step, i // per_seed, i % per_seed, r, "mjx", "clean", 0])
    return str(path)


def test_line_measures_prints_each_runs_value_the_lines_mean_and_pooled_lines(tmp_path, capsys):
    a1 = _run(tmp_path / "a1", {100: {0: [0, 10]}, 200: {0: [20, 40]}, 300: {0: [100, 200]}, 400: {0: [300, 500]}})
    a2 = _run(tmp_path / "a2", {100: {0: [5]}, 200: {0: [5]}, 300: {0: [5]}, 400: {0: [200]}})
    b1 = _run(tmp_path / "b1", {400: {0: [100, 300], 1: [600, 600]}})  # two seeds: mean of seed means (200, 600)
    b2 = _run(tmp_path / "b2", {400: {0: [0]}})
    mjx_a = [_eval_csv(tmp_path / "a1.csv", [10, 20, 30]), _eval_csv(tmp_path / "a2.csv", [40, 40])]
    mjx_b = [_eval_csv(tmp_path / "b1.csv", [0, 100, 50, 50], seeds=2), _eval_csv(tmp_path / "b2.csv", [70])]
    out = tmp_path / "table.md"
    code = line_measures.main(["--line", f"A={a1},{a2}", "--line", f"B={b1},{b2}",
                               "--csv", f"A:MJX={','.join(mjx_a)}", "--csv", f"B:MJX={','.join(mjx_b)}",
                               "--pool", "both=A+B", "--out", str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    assert printed == out.read_text()
    rows = printed.splitlines()
    assert rows[0] == "| line | trainer's last evaluation | mean of the last 3 evaluations | MJX |"
    # a1: last 400.0, last three (30 + 150 + 400) / 3 = 193.3; a2: 200.0 and (5 + 5 + 200) / 3 = 70.0
    assert rows[2] == ("| A | 400.0 / 200.0: **300.0** | 193.3 / 70.0: **131.7** | 20.0 / 40.0: **30.0** |")
    # b1: its one evaluation (mean of the seeds' means, 200 and 600) is its last three too
    assert rows[3] == ("| B | 400.0 / 0.0: **200.0** | 400.0 / 0.0: **200.0** | 50.0 / 70.0: **60.0** |")
    assert rows[4] == "| both (A + B) | pooled **250.0** | pooled **165.8** | pooled **45.0** |"


def test_line_measures_leaves_a_pooled_cell_empty_where_a_line_lacks_the_measure(tmp_path, capsys):
    a = _run(tmp_path / "a", {100: {0: [10]}})
    b = _run(tmp_path / "b", {100: {0: [30]}})
    assert line_measures.main(["--line", f"A={a}", "--line", f"B={b}", "--csv",
                               f"A:dm_control={_eval_csv(tmp_path / 'a.csv', [1, 3])}", "--pool", "AB=A+B"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows[3] == "| B | 30.0: **30.0** | 30.0: **30.0** |  |"
    assert rows[4] == "| AB (A + B) | pooled **20.0** | pooled **20.0** |  |"


@pytest.mark.parametrize("arguments, message", [
    (["--line", "A"], "--line takes LABEL=RUN[,RUN...], got 'A'"),
    (["--line", "A={a}", "--line", "A={a}"], "--line 'A' given twice"),
    (["--line", "A={a}", "--csv", "C:MJX={c}"], "no --line 'C'; the lines: A"),
    (["--line", "A={a}", "--csv", "A={c}"], "--csv takes LABEL:MEASURE=CSV[,CSV...], got 'A="),
    (["--line", "A={a}", "--csv", "A:MJX={c},{c}"], "names 2 CSV(s) for the line's 1 run(s)"),
    (["--line", "A={a}", "--csv", "A:MJX={c}", "--csv", "A:MJX={c}"], "gives measure 'MJX' of line 'A' twice"),
    (["--line", "A={a}", "--pool", "P=A+Z"], "--pool 'P': no --line 'Z'; the lines: A"),
    (["--line", "A={a}", "--pool", "A=A+A"], "--pool label 'A' is already taken"),
    (["--line", "A={a},{late}"], "its runs last evaluated at different steps"),
    (["--line", "A={tmp}/missing"], "has no eval.csv"),
    (["--line", "A={a}", "--csv", "A:MJX={a}/eval.csv"], "is not a CSV of `cli eval`"),
])
def test_line_measures_refuses_bad_input_naming_it(tmp_path, capsys, arguments, message):
    values = {"a": _run(tmp_path / "a", {100: {0: [1]}}), "late": _run(tmp_path / "late", {200: {0: [1]}}),
              "c": _eval_csv(tmp_path / "c.csv", [1]), "tmp": str(tmp_path)}
    assert line_measures.main([a.format(**values) for a in arguments]) == 2
    assert message in capsys.readouterr().err
