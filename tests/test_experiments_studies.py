"""Study grids, resume decisions, table rows and condition selection of lnnmpc.experiments, on fake run folders
(no training)."""

import csv
import dataclasses
import os

import pytest
from run_folders import fake_run

import lnnmpc
from lnnmpc.experiments import grid, run
from lnnmpc.experiments.aggregate import markdown, study_rows
from lnnmpc.experiments.thesis import eval_key
from lnnmpc.train.config import ConfigError


@pytest.mark.parametrize("name, runs, rows", [("table5_3", 28, 28), ("table5_4", 14, 28), ("table5_5", 7, 21),
                                              ("table5_6", 7, 21), ("fig5_18", 12, 12), ("fig5_19", 1, 5)])
def test_study_grid_sizes(tmp_path, name, runs, rows):
    options = grid.GridOptions(runs_dir=str(tmp_path))
    specs = grid.expand(grid.get_study(name), options)
    assert len(specs) == runs
    assert len({s.folder for s in specs}) == runs
    assert len(study_rows(grid.get_study(name), specs, options.steps)) == rows
    assert all(s.config.steps == 200_000 and s.config.seeds == 3 for s in specs)


def test_noise_study_folders_and_corruptions(tmp_path):
    options = grid.GridOptions(runs_dir=str(tmp_path), seeds=2, agents=("tdmpc2",))
    specs = grid.expand(grid.get_study("table5_4"), options)
    assert [s.folder for s in specs] == [str(tmp_path / "cartpole-swingup" / "tdmpc2" / "novel-seeds2"),
                                        str(tmp_path / "cartpole-swingup" / "tdmpc2" / "flicker0.2-noise0.1-seeds2")]
    assert specs[1].config.obs == {"obs_noise": 0.1, "flicker": 0.2}
    assert [eval_key(o) for o in specs[1].condition.eval_obs] == [
        "flicker0.2-noise0.1", "flicker0.2-noise0.2", "flicker0.2-noise0.3"]
    assert grid.expand(grid.get_study("table5_4"), options) == specs  # deterministic
    small = grid.GridOptions(runs_dir="r", envs=2, model_size=1, small=True)
    assert grid.run_folder("r", "walker-run", "tdmpc2", "delay=2", small).endswith("delay2-seeds3-envs2-size1-small")
    delays = [s.config.obs["delay"] for s in grid.expand(grid.get_study("fig5_18"), options)]
    assert delays == [3, 6, 10, 1, 2, 3]


def test_bad_names_are_refused():
    with pytest.raises(ConfigError, match="ltc-zp-stoch.*its agents: tdmpc2, ltc-zp-det"):
        grid.expand(grid.get_study("fig5_18"), grid.GridOptions(agents=("ltc-zp-stoch",)))
    with pytest.raises(ConfigError, match="unknown study 'table9'.*table5_3"):
        grid.get_study("table9")
    with pytest.raises(ConfigError, match="seeds must be an integer >= 1, got 0"):
        grid.GridOptions(seeds=0)


def test_run_status(tmp_path):
    assert grid.run_status(str(tmp_path / "none"), 200_000) == "new"
    fake_run(str(tmp_path / "done"), 200_016)
    fake_run(str(tmp_path / "short"), 150_000)
    fake_run(str(tmp_path / "nockpt"), 200_016, checkpoint=False)
    assert grid.run_status(str(tmp_path / "done"), 200_000) == "finished"
    assert grid.run_status(str(tmp_path / "short"), 200_000) == "partial"
    assert grid.run_status(str(tmp_path / "nockpt"), 200_000) == "partial"
    assert grid.checkpoint_steps(str(tmp_path / "done")) == [200_016]


def test_rerun_skips_finished_runs_and_resumes_the_others(tmp_path, monkeypatch):
    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, agents=("tdmpc2", "cfc-zp-det"))
    specs = grid.expand(grid.get_study("table5_5"), options)
    fake_run(specs[0].folder, 50_000)  # finished
    fake_run(specs[1].folder, 20_000)  # partial: resumed through lnnmpc.train with the same folder
    trained = []
    monkeypatch.setattr(lnnmpc, "train", lambda config: trained.append(config))
    lines = run.run_study("table5_5", options, out=str(tmp_path / "out"), evaluate=False)
    assert [c.out for c in trained] == [specs[1].folder]
    assert trained[0] == specs[1].config
    assert lines == [f"wrote {tmp_path / 'out' / 'table5_5.csv'}", f"wrote {tmp_path / 'out' / 'table5_5.md'}"]
    assert run.missing_evaluations(specs[0], options) == [(o, None) for o in specs[0].condition.eval_obs]
    os.makedirs(os.path.join(specs[0].folder, "evals"))
    open(grid.eval_file(specs[0].folder, 50_000, "noise=0.2"), "w").close()
    assert [o for o, _ in run.missing_evaluations(specs[0], options)] == ["noise=0.1", "noise=0.3"]


def test_eval_cadence_applies_to_new_runs_and_existing_runs_keep_their_own(tmp_path, monkeypatch):
    """``--eval-every`` sets the training-time evaluations of runs a study creates; a folder that exists was
    created with a cadence the trainer will not resume under another, so the study passes that one on."""
    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, agents=("tdmpc2", "cfc-zp-det"),
                               eval_every=25_000)
    old, new = grid.expand(grid.get_study("table5_5"), options)
    os.makedirs(old.folder)
    with open(os.path.join(old.folder, "config.json"), "w") as f:
        f.write('{"config": {"eval_every": 10000}}')
    old, new = grid.expand(grid.get_study("table5_5"), options)
    assert (old.config.eval_every, new.config.eval_every) == (10_000, 25_000)
    assert grid.saved_eval_every(new.folder) is None
    with open(os.path.join(old.folder, "config.json"), "w") as f:
        f.write('{"config": {"eval_every": "often"}}')
    assert grid.saved_eval_every(old.folder) is None  # unreadable: the study's own cadence
    trained = []
    monkeypatch.setattr(lnnmpc, "train", lambda config: trained.append(config.eval_every))
    assert run.main(["table5_5", "--steps", "50000", "--agents", "cfc-zp-det", "--eval-every", "20000",
                     "--runs-dir", str(tmp_path), "--out", str(tmp_path / "out")]) == 0
    assert trained == [20_000]
    with pytest.raises(ConfigError, match="eval_every must be an integer >= 1, got 0"):
        grid.GridOptions(eval_every=0)


def test_eval_prior_reaches_every_run_of_a_study(tmp_path, monkeypatch):
    """``--eval-prior``: each run's training-time evaluations also play the policy prior alone; off by default."""
    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, agents=("tdmpc2", "cfc-zp-det"))
    assert not any(s.config.eval_prior for s in grid.expand(grid.get_study("table5_5"), options))
    prior = dataclasses.replace(options, eval_prior=True)
    assert all(s.config.eval_prior for s in grid.expand(grid.get_study("table5_5"), prior))
    trained = []
    monkeypatch.setattr(lnnmpc, "train", lambda config: trained.append((config.agent, config.eval_prior)))
    assert run.main(["table5_5", "--steps", "50000", "--agents", "tdmpc2,cfc-zp-det", "--eval-prior", "--runs-dir",
                     str(tmp_path), "--out", str(tmp_path / "out")]) == 0
    assert trained and all(on for _, on in trained) and {a for a, _ in trained} == {"tdmpc2", "cfc-zp-det"}
    with pytest.raises(ConfigError, match="eval_prior must be True or False, got 'yes'"):
        grid.GridOptions(eval_prior="yes")


def test_tables_list_every_agent_whose_run_exists_besides_the_requested_ones(tmp_path):
    """Two studies of one table run side by side (``--agents tdmpc2`` and ``--agents cfc-zp-det``): whichever
    aggregates last still lists both agents' cells, and agents with no run folder are left out."""
    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, agents=("cfc-zp-det",))
    other = grid.expand(grid.get_study("table5_5"), grid.GridOptions(runs_dir=str(tmp_path), steps=50_000,
                                                                      agents=("tdmpc2",)))[0]
    fake_run(other.folder, 50_000, returns=[[10.0, 30.0]], eval_name="mjx-noise0.1-50000.csv")
    run.run_study("table5_5", options, out=str(tmp_path / "out"), train=False, evaluate=False)
    with open(tmp_path / "out" / "table5_5.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert sorted({r["agent"] for r in rows}) == ["cfc-zp-det", "tdmpc2"]
    measured = [r for r in rows if r["agent"] == "tdmpc2" and r["eval_obs"] == "noise0.1"]
    assert len(measured) == 1 and float(measured[0]["mean"]) == 20.0
    assert all(r["mean"] == "" for r in rows if r["agent"] == "cfc-zp-det")
    assert not [p for p in os.listdir(tmp_path / "out") if p.endswith(".tmp")]


def test_tables_find_runs_made_with_other_environments_per_seed(tmp_path):
    """Table 5.3 filled by a walker run with 16 environments per seed and a cartpole run with 8: aggregating with
    ``--envs 8`` still lists the walker cell (from the sibling evaluated the furthest), and a different seed
    count or corruption is never taken for the same run."""
    runs = tmp_path / "runs"
    walker = runs / "walker-run" / "cfc-zp-det"
    fake_run(str(walker / "clean-seeds3-envs16"), 140_000, returns=[[600.0, 700.0]], eval_name="mjx-clean-140000.csv")
    fake_run(str(walker / "clean-seeds3-envs4"), 60_000, returns=[[100.0, 100.0]], eval_name="mjx-clean-60000.csv")
    fake_run(str(walker / "clean-seeds2-envs16"), 190_000, returns=[[1.0, 1.0]], eval_name="mjx-clean-190000.csv")
    fake_run(str(walker / "noise0.1-seeds3-envs16"), 190_000, returns=[[2.0, 2.0]], eval_name="mjx-clean-190000.csv")
    sparse = runs / "cartpole-swingup-sparse" / "tdmpc2" / "clean-seeds3-envs8"
    fake_run(str(sparse), 200_000, returns=[[800.0, 820.0]], eval_name="mjx-clean-200000.csv")
    assert grid.measured_elsewhere(str(walker / "clean-seeds3-envs8")) == (str(walker / "clean-seeds3-envs16"), 16)
    assert grid.measured_elsewhere(str(walker / "clean-seeds3")) == (str(walker / "clean-seeds3-envs16"), 16)
    assert grid.measured_elsewhere(str(walker / "clean-seeds4-envs8")) is None
    assert grid.measured_elsewhere(str(runs / "acrobot-swingup" / "tdmpc2" / "clean-seeds3-envs8")) is None
    options = grid.GridOptions(runs_dir=str(runs), envs=8, agents=("tdmpc2",))
    run.run_study("table5_3", options, out=str(tmp_path / "out"), train=False, evaluate=False)
    with open(tmp_path / "out" / "table5_3.csv", newline="") as f:
        rows = {(r["task"], r["agent"]): r for r in csv.DictReader(f)}
    assert float(rows["walker-run", "cfc-zp-det"]["mean"]) == 650.0
    assert rows["walker-run", "cfc-zp-det"]["run"].endswith("clean-seeds3-envs16")
    assert float(rows["cartpole-swingup-sparse", "tdmpc2"]["mean"]) == 810.0
    assert rows["walker-run", "tdmpc2"]["mean"] == ""


def test_dry_run_lists_the_grid(tmp_path, capsys):
    assert run.main(["fig5_18", "--dry-run", "--runs-dir", str(tmp_path), "--seeds", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "fig5_18: 12 runs of 2 seed(s) x 200,000 env steps"
    assert len(out) == 13 and all(line.startswith("[new     ]") for line in out[1:])
    assert not os.listdir(tmp_path)
    assert run.main(["fig5_18", "--agents", "cfc-op-det", "--dry-run"]) == 2


def test_recipes_give_the_matching_runs_their_settings_and_folders(tmp_path, capsys):
    options = grid.GridOptions(runs_dir=str(tmp_path), recipes=True)
    specs = {(s.condition.task, s.agent): s for s in grid.expand(grid.get_study("table5_3"), options)}
    sparse = specs["cartpole-swingup-sparse", "cfc-op-det"]
    assert sparse.recipe == "sparse"
    assert sparse.folder == str(tmp_path / "cartpole-swingup-sparse" / "cfc-op-det"
                                / "clean-seeds3-envs8-recipe-sparse")
    config = sparse.config
    assert (config.envs, config.seed_steps, config.explore_noise_beta, config.seed_noise_beta) == (8, 20_000, 1.0, 1.0)
    assert config.overrides == {"lambda_": 0, "lr_decay_begin": 50_000, "lr_decay_end": 100_000, "lr_final_scale": 0.1}
    acrobot = specs["acrobot-swingup", "cfc-zp-det"]
    assert acrobot.recipe == "acrobot" and acrobot.config.envs == 16 and acrobot.config.action_repeat == 6
    assert acrobot.folder.endswith("-envs16-recipe-acrobot")
    assert sorted(s.recipe for s in specs.values() if s.recipe) == ["acrobot", "sparse"]  # 2 of 28 runs
    plain = specs["cartpole-swingup-sparse", "tdmpc2"]
    assert plain.folder.endswith("clean-seeds3") and plain.config.envs == 1 and plain.config.overrides == {}
    assert plain == grid.expand(grid.get_study("table5_3"), grid.GridOptions(runs_dir=str(tmp_path)))[7]
    noisy = {(s.condition.train_obs, s.agent): s for s in grid.expand(grid.get_study("table5_4"), options)}
    assert noisy["remove_vel=1", "cfc-zp-det"].recipe == "remove-vel"  # its corruption matches; the noisy one does not
    assert noisy["remove_vel=1", "cfc-zp-det"].config.overrides["num_q"] == 5
    assert not noisy["noise=0.1,flicker=0.2", "cfc-zp-det"].recipe
    short = grid.expand(grid.get_study("table5_3"), dataclasses.replace(options, steps=10_000))
    assert {s.config.seed_steps for s in short} == {5000, 10_000}  # the recipe's 20K seed phase capped at the budget
    study = grid.get_study("table5_3")
    text = markdown(study, study_rows(study, list(specs.values()), options.steps))
    assert "| cartpole-swingup-sparse | clean | clean | cfc-op-det (recipe `sparse`) | not yet run |" in text
    assert "| cartpole-swingup-sparse | clean | clean | tdmpc2 | not yet run |" in text
    assert run.main(["table5_3", "--recipes", "--agents", "cfc-op-det", "--tasks", "cartpole-swingup-sparse",
                     "--dry-run", "--runs-dir", str(tmp_path)]) == 0
    assert "cfc-op-det/clean-seeds3-envs8-recipe-sparse" in capsys.readouterr().out
    with pytest.raises(ConfigError, match="recipes must be True or False, got 'yes'"):
        grid.GridOptions(recipes="yes")


def test_select_conditions_by_task_and_training_corruption(tmp_path, capsys):
    options = grid.GridOptions(runs_dir=str(tmp_path), agents=("tdmpc2",))
    specs = grid.expand(grid.get_study("table5_3"), options)
    walker = run.select_conditions(specs, ("walker-run", "acrobot-swingup"), None)
    assert [s.condition.task for s in walker] == ["acrobot-swingup", "walker-run"]
    assert run.select_conditions(specs, None, "clean") == specs and run.select_conditions(specs, None, None) == specs
    noisy = grid.expand(grid.get_study("table5_4"), options)
    flicker = run.select_conditions(noisy, ("cartpole-swingup",), "noise=0.1,flicker=0.2")
    assert len(flicker) == 1 and flicker[0].config.obs == {"obs_noise": 0.1, "flicker": 0.2}
    assert run.select_conditions(noisy, None, "flicker=0.2,obs_noise=0.1") == flicker  # options, not text
    with pytest.raises(ConfigError, match="bad observation option 'nosie'"):
        run.select_conditions(noisy, None, "nosie=0.1")
    with pytest.raises(ConfigError, match="task.s. walker-fly are not in this study; its tasks: acrobot-swingup"):
        run.select_conditions(specs, ("walker-fly",), None)
    with pytest.raises(ConfigError, match="no condition trains under 'noise=0.5'; the study's: noise=0.1,flicker"):
        run.select_conditions(noisy, None, "noise=0.5")
    assert run.main(["table5_3", "--agents", "tdmpc2", "--tasks", "walker-run,cartpole-swingup", "--dry-run",
                     "--runs-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "table5_3: 2 runs of 3 seed(s) x 200,000 env steps" and len(out) == 3
    assert run.main(["table5_4", "--train-obs", "delay=3", "--dry-run", "--runs-dir", str(tmp_path)]) == 2
