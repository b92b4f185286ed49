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
