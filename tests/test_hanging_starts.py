"""``python -m lnnmpc.analysis.hanging_starts`` on hand-made acrobot_starts CSVs and run folders: the energy cut per
source kind, the means below and above it, the policy prior's returns from eval.csv, repeated rows, bad input."""

import csv
import os

import numpy as np
import pytest

from lnnmpc.analysis import hanging_starts
from lnnmpc.train.config import ConfigError

FIELDS = ["run", "source", "seed", "episode", "shoulder", "elbow", "energy", "return"]


def _write_csv(path, rows, fields=FIELDS):
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def _starts(tmp_path):
    """Two lines x two master seeds; three training starts per master seed (energies -9..-4 J) and four shared
    MJX starts (-20, -10, 0, 10 J). Line A's run of master seed 1 has an eval.csv with prior returns."""
    rows = []
    for line, offset in (("line-a", 0.0), ("line-b", 100.0)):
        for seed in (1, 2):
            run = str(tmp_path / f"{line}-seed{seed}")
            os.makedirs(run, exist_ok=True)
            for episode in range(3):
                energy = -10.0 + 3 * (seed - 1) + episode + 1  # seed 1: -9, -8, -7; seed 2: -6, -5, -4
                rows.append({"run": run, "source": "training evaluation 200256", "seed": 0, "episode": episode,
                             "shoulder": 0, "elbow": 0, "energy": energy, "return": offset + 10 * energy + 200})
            for episode, energy in enumerate((-20.0, -10.0, 0.0, 10.0)):
                rows.append({"run": run, "source": f"mjx-20ep-{line}-seed{seed}-200256.csv", "seed": 0,
                             "episode": episode, "shoulder": 0, "elbow": 0, "energy": energy,
                             "return": offset + energy + 500})
    _write_csv(tmp_path / "line-a-seed1" / "eval.csv",
               [{"env_step": step, "seed": 0, "episode": e, "return": 1.0, "prior_return": 7.0 * (e + 1) + step % 7}
                for step in (161184, 200256) for e in range(3)],
               ["env_step", "seed", "episode", "return", "prior_return"])
    return rows


def test_split_table_cuts_each_source_kind_at_its_lowest_third(tmp_path):
    rows = _starts(tmp_path)
    _write_csv(tmp_path / "starts.csv", rows)
    table = hanging_starts.split_table(hanging_starts.read_starts([str(tmp_path / "starts.csv")]), 1 / 3)
    lines = table.splitlines()
    # six distinct training energies -9..-4: the lowest two (-9, -8) below -7; four MJX energies: -20 below -10
    assert lines[0] == ("Starts split at the lowest 0.33 of each source's distinct start energies: training "
                        "evaluation below -7.00 J; mjx-20ep below -10.00 J.")
    training_a_low = np.mean([10 * e + 200 for e in (-9, -8)])
    training_a_high = np.mean([10 * e + 200 for e in (-7, -6, -5, -4)])
    # line A's prior: only master seed 1's run has an eval.csv; its episodes 0, 1 (energies -9, -8) lie below, 2 above
    prior_low, prior_high = np.mean([7.0 * 1 + 200256 % 7, 7.0 * 2 + 200256 % 7]), 7.0 * 3 + 200256 % 7
    assert lines[4:] == [
        f"| line-a | training evaluation | 2 / 4 | {training_a_low:.1f} | {training_a_high:.1f} | {prior_low:.1f} | "
        f"{prior_high:.1f} |",
        f"| line-a | mjx-20ep | 2 / 6 | {-20 + 500:.1f} | {np.mean([-10, 0, 10]) + 500:.1f} |  |  |",
        f"| line-b | training evaluation | 2 / 4 | {training_a_low + 100:.1f} | {training_a_high + 100:.1f} |  |  |",
        f"| line-b | mjx-20ep | 2 / 6 | {-20 + 600:.1f} | {np.mean([-10, 0, 10]) + 600:.1f} |  |  |"]


def test_rows_repeated_across_csvs_count_once_and_the_command_writes_its_table(tmp_path, capsys):
    rows = _starts(tmp_path)
    _write_csv(tmp_path / "first.csv", rows[:10])
    _write_csv(tmp_path / "second.csv", rows)  # its first 10 rows again
    once = hanging_starts.read_starts([str(tmp_path / "first.csv"), str(tmp_path / "second.csv")])
    assert len(once) == len(rows)
    out = tmp_path / "table.md"
    assert hanging_starts.main([str(tmp_path / "first.csv"), str(tmp_path / "second.csv"), "--fraction", "0.5",
                                "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed == out.read_text() and "lowest 0.50" in printed and "| line-b | mjx-20ep | 4 / 4 |" in printed


def test_source_kinds_line_names_and_the_cut_of_one_start():
    assert hanging_starts.source_kind("training evaluation 161184") == "training evaluation"
    assert hanging_starts.source_kind("mjx-20ep-gamma985-relaunch-seed2-200256.csv") == "mjx-20ep"
    assert hanging_starts.source_kind("dm_control-gpu-explorefloor05-seed1-200256.csv") == "dm_control-gpu"
    assert hanging_starts.source_kind("a/b/dm_control-iter12-seed3-200256.csv") == "dm_control"
    assert hanging_starts.source_kind("mjx-cpu-20ep-floor-seed1-200256-pi128.csv") == "mjx-cpu-20ep -pi128"
    assert hanging_starts.line_name("x/acrobot-recipe-explorefloor02-seed3/") == "acrobot-recipe-explorefloor02"
    assert hanging_starts.energy_cut([3.0, 3.0], 0.1) == float("inf")  # one distinct start: it counts as hanging
    assert hanging_starts.energy_cut([5.0, 1.0, 3.0, 1.0], 0.01) == 3.0  # at least the lowest one below


def test_bad_input_is_named(tmp_path, capsys):
    with pytest.raises(ConfigError, match="no such file"):
        hanging_starts.read_starts([str(tmp_path / "gone.csv")])
    _write_csv(tmp_path / "short.csv", [{"run": "r", "source": "s"}], ["run", "source", "seed"])
    with pytest.raises(ConfigError, match=r"lacks the column\(s\) episode, energy, return"):
        hanging_starts.read_starts([str(tmp_path / "short.csv")])
    _write_csv(tmp_path / "empty.csv", [])
    with pytest.raises(ConfigError, match="no episodes in"):
        hanging_starts.read_starts([str(tmp_path / "empty.csv")])
    _write_csv(tmp_path / "starts.csv", _starts(tmp_path))
    for fraction in ("0", "1", "1.5"):
        assert hanging_starts.main([str(tmp_path / "starts.csv"), "--fraction", fraction]) == 2
        assert capsys.readouterr().err == f"error: --fraction {float(fraction)} must lie strictly between 0 and 1\n"
