"""Study grids, resume decisions and aggregation of lnnmpc.experiments, on fake run folders (no training)."""

import csv
import dataclasses
import os

import numpy as np
import pytest

import lnnmpc
from lnnmpc.experiments import grid, run
from lnnmpc.experiments.aggregate import markdown, newest_eval, read_returns, study_rows, summarize
from lnnmpc.experiments.thesis import eval_key, tdmpc2_value, thesis_value
from lnnmpc.train.config import ConfigError


def _write(path, rows):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _fake_run(folder, last_step, checkpoint=True, returns=None, eval_name=None):
    """A run folder with config.json, eval.csv up to ``last_step`` and optionally a checkpoint at it."""
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "config.json"), "w") as f:
        f.write('{"config": {}}')
    _write(os.path.join(folder, "eval.csv"), [{"env_step": s, "seed": 0, "episode": 0, "return": 1.0}
                                              for s in (10_000, last_step)])
    if checkpoint:
        os.makedirs(os.path.join(folder, "checkpoints", str(last_step)))
    if returns is not None:
        _write(os.path.join(folder, "evals", eval_name),
               [{"env_step": last_step, "seed": s, "episode": e, "return": returns[s][e]}
                for s in range(len(returns)) for e in range(len(returns[0]))])


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
    _fake_run(str(tmp_path / "done"), 200_016)
    _fake_run(str(tmp_path / "short"), 150_000)
    _fake_run(str(tmp_path / "nockpt"), 200_016, checkpoint=False)
    assert grid.run_status(str(tmp_path / "done"), 200_000) == "finished"
    assert grid.run_status(str(tmp_path / "short"), 200_000) == "partial"
    assert grid.run_status(str(tmp_path / "nockpt"), 200_000) == "partial"
    assert grid.checkpoint_steps(str(tmp_path / "done")) == [200_016]


def test_rerun_skips_finished_runs_and_resumes_the_others(tmp_path, monkeypatch):
    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, agents=("tdmpc2", "cfc-zp-det"))
    specs = grid.expand(grid.get_study("table5_5"), options)
    _fake_run(specs[0].folder, 50_000)  # finished
    _fake_run(specs[1].folder, 20_000)  # partial: resumed through lnnmpc.train with the same folder
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
    _fake_run(other.folder, 50_000, returns=[[10.0, 30.0]], eval_name="mjx-noise0.1-50000.csv")
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
    _fake_run(str(walker / "clean-seeds3-envs16"), 140_000, returns=[[600.0, 700.0]], eval_name="mjx-clean-140000.csv")
    _fake_run(str(walker / "clean-seeds3-envs4"), 60_000, returns=[[100.0, 100.0]], eval_name="mjx-clean-60000.csv")
    _fake_run(str(walker / "clean-seeds2-envs16"), 190_000, returns=[[1.0, 1.0]], eval_name="mjx-clean-190000.csv")
    _fake_run(str(walker / "noise0.1-seeds3-envs16"), 190_000, returns=[[2.0, 2.0]], eval_name="mjx-clean-190000.csv")
    sparse = runs / "cartpole-swingup-sparse" / "tdmpc2" / "clean-seeds3-envs8"
    _fake_run(str(sparse), 200_000, returns=[[800.0, 820.0]], eval_name="mjx-clean-200000.csv")
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
    assert acrobot.recipe == "acrobot" and acrobot.config.envs == 16 and acrobot.config.action_repeat == 4
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


DEVICE_BATCH = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "device_batch.sh")


def test_device_batch_check_validates_every_job_line(tmp_path):
    """``device_batch.sh check``: each line of a jobs file validated on the CPU before any device time."""
    import subprocess
    import sys

    script = DEVICE_BATCH
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("# a comment\n\n"
                    "study-ok   experiment fig5_19 --small --seeds 1\n"
                    "train-bad  --task cartpole-balance --small --set lamda=0\n"
                    "pin-bad@x  --task cartpole-balance --small\n")
    result = subprocess.run(["bash", script, "check", str(jobs)], capture_output=True, text=True, timeout=300,
                            env={**os.environ, "PYTHON": sys.executable, "JAX_PLATFORMS": "cpu"}, cwd=tmp_path)
    assert result.returncode == 1, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == "ok      study-ok"
    assert lines[1].startswith("FAILED  train-bad: error: unknown hyperparameter 'lamda'")
    assert lines[2] == "FAILED  pin-bad@x: bad GPU 'x' in job name 'pin-bad@x': give <name>@<number> or <name>@all"
    assert sorted(os.listdir(tmp_path)) == ["jobs.txt"]  # nothing written beside it


def _fake_gpu_machine(tmp_path, gpus: int, python_body: str, **extra) -> dict:
    """The environment of a fake GPU machine for ``device_batch.sh``: an ``nvidia-smi`` that lists ``gpus`` GPUs
    and a PYTHON that runs the shell ``python_body``; no OUT, MEM_FRACTION or FORCE from outside; ``extra`` added."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    listing = "".join(f"GPU {i}: fake\\n" for i in range(gpus))
    (bin_dir / "nvidia-smi").write_text(f'#!/bin/sh\n[ "$1" = -L ] && printf "{listing}"\nexit 0\n')
    (bin_dir / "fake-python").write_text(f"#!/bin/sh\n{python_body}\n")
    for tool in ("nvidia-smi", "fake-python"):
        os.chmod(bin_dir / tool, 0o755)
    env = {k: v for k, v in os.environ.items() if k not in ("OUT", "MEM_FRACTION", "FORCE")}
    return {**env, "PATH": f"{bin_dir}:{os.environ['PATH']}", "PYTHON": str(bin_dir / "fake-python"), **extra}


def test_device_batch_check_gives_an_all_gpu_job_its_devices(tmp_path):
    """``check`` of a ``<name>@all`` line runs it with as many host devices as its ``--devices`` asks (the CPU
    has one; the job sees every GPU of the machine), and a pinned line with one device."""
    import subprocess

    body = ('case "$XLA_FLAGS" in *host_platform_device_count=4*) exit 0;; esac; '
            'echo "error: devices=4 but only 1 device(s) exist"; exit 1')
    env = _fake_gpu_machine(tmp_path, 1, body, XLA_FLAGS="--xla_dump_to=/nowhere")
    results = {}
    for name in ("sharded@all", "pinned@0"):
        jobs = tmp_path / f"{name}.txt"
        jobs.write_text(f"{name} --task walker-run --seeds 4 --devices 4 --steps 200\n")
        run = subprocess.run(["bash", DEVICE_BATCH, "check", str(jobs)], capture_output=True, text=True,
                             timeout=60, env=env, cwd=tmp_path)
        results[name] = (run.returncode, run.stdout.strip())
    assert results["sharded@all"] == (0, "ok      sharded")
    assert results["pinned@0"] == (1, "FAILED  pinned: error: devices=4 but only 1 device(s) exist")


def test_device_batch_start_places_pinned_and_round_robin_jobs(tmp_path):
    """``device_batch.sh start`` on a fake two-GPU machine (an ``nvidia-smi`` that lists two GPUs, a PYTHON that
    prints its GPU and memory share): ``name@k`` lines go to GPU k mod 2, the others round robin by position,
    each process gets 0.9 / (jobs on its GPU) of the memory; a GPU that is no number stops it before any launch."""
    import subprocess

    script = DEVICE_BATCH
    env = _fake_gpu_machine(tmp_path, 2, 'echo "gpu=$CUDA_VISIBLE_DEVICES mem=$XLA_PYTHON_CLIENT_MEM_FRACTION"')
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("a    --task cartpole-balance\nb@0  --task cartpole-balance\n"
                    "c    --task cartpole-balance\nd@3  --task cartpole-balance\n")
    result = subprocess.run(["bash", script, "start", str(jobs), "60", "20"], capture_output=True, text=True,
                            timeout=120, env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    batch = tmp_path / "runs" / "batch"
    assert (batch / "gpus.txt").read_text() == "4 jobs on 2 GPU(s), up to 3 per GPU\n"
    commands = (batch / "commands.txt").read_text().splitlines()
    assert [line.split(":")[0] for line in commands] == ["a (GPU 0)", "b (GPU 0)", "c (GPU 0)", "d (GPU 1)"]
    logs = {name: (batch / f"{name}.log").read_text().strip() for name in "abcd"}
    assert logs == {"a": "gpu=0 mem=0.3", "b": "gpu=0 mem=0.3", "c": "gpu=0 mem=0.3", "d": "gpu=1 mem=0.9"}
    jobs.write_text("a@one  --task cartpole-balance\n")
    result = subprocess.run(["bash", script, "start", str(jobs), "60", "20"], capture_output=True, text=True,
                            timeout=120, env=env, cwd=tmp_path)
    assert result.returncode == 2 and "bad GPU 'one' in job name 'a@one'" in result.stderr
    assert len((batch / "commands.txt").read_text().splitlines()) == 4  # nothing launched
    jobs.write_text("sharded@all  --task cartpole-balance --seeds 2 --devices 2\n")  # one job, every GPU
    result = subprocess.run(["bash", script, "start", str(jobs), "60", "20"], capture_output=True, text=True,
                            timeout=120, env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert (batch / "sharded.log").read_text().strip() == "gpu=0,1 mem=0.9"
    assert (batch / "commands.txt").read_text().splitlines()[-1].startswith("sharded (GPU all): --task")
    jobs.write_text("sharded@all  --task cartpole-balance\nother  --task cartpole-balance\n")
    result = subprocess.run(["bash", script, "start", str(jobs), "60", "20"], capture_output=True, text=True,
                            timeout=120, env=env, cwd=tmp_path)
    assert result.returncode == 2 and "a <name>@all job uses every GPU: give it a jobs file of its own" in result.stderr


def test_device_batch_after_runs_a_command_once_its_job_has_ended(tmp_path):
    """``device_batch.sh after NAME GPU CMD``: each job records its exit status (NAME.rc) when it ends; the command
    waits for that in the background, then runs on the given GPU; an unknown job or a GPU that is no number is
    refused at once, naming the batch's jobs."""
    import subprocess
    import time

    script = DEVICE_BATCH
    env = _fake_gpu_machine(tmp_path, 2, "exit 3", AFTER_POLL="0.05")
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("a@0  --task cartpole-balance\n")
    run = lambda *args: subprocess.run(["bash", script, *args], capture_output=True, text=True, timeout=60, env=env,
                                       cwd=tmp_path)
    batch = tmp_path / "runs" / "batch"

    def wait_for(path, text):  # the background command's output, within 20 s
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            if path.exists() and text in path.read_text():
                return path.read_text()
            time.sleep(0.05)
        raise AssertionError(f"{path}: no {text!r} in {path.read_text() if path.exists() else 'no file'}")

    assert run("start", str(jobs), "60", "5").returncode == 0
    assert wait_for(batch / "a.rc", "3").strip() == "3"  # the job's exit status
    assert 0 <= float((batch / "a.seconds").read_text()) < 60  # and its wall time, launch to exit
    report = run("wait", "0")
    assert report.returncode == 0 and f"ended (exit 3) {(batch / 'a.seconds').read_text().strip()} s after" in (
        report.stdout)
    # a job still running: the command waits for its .rc
    with open(batch / "commands.txt", "a") as f:
        f.write("b (GPU 1): --task cartpole-balance\n")
    assert run("after", "b", "1", "sh", "-c", "echo ran on $CUDA_VISIBLE_DEVICES").returncode == 0
    assert run("after", "a", "0", "sh", "-c", "echo ran on $CUDA_VISIBLE_DEVICES").returncode == 0
    assert "ran on 0" in wait_for(batch / "after-a.log", "ran on")
    assert "a ended (exit 3)" in (batch / "after-a.log").read_text()
    assert "ran on" not in (batch / "after-b.log").read_text()
    (batch / "b.rc").write_text("0\n")
    assert "ran on 1" in wait_for(batch / "after-b.log", "ran on")
    refused = run("after", "zz", "1", "true")
    assert refused.returncode == 2 and "no job 'zz'" in refused.stderr and "(jobs: a b )" in refused.stderr
    refused = run("after", "a", "x", "true")
    assert refused.returncode == 2 and "bad GPU 'x'" in refused.stderr


def test_device_batch_start_refuses_while_an_earlier_starts_jobs_run(tmp_path):
    """A second ``start`` in one hold (the next jobs file): refused, naming them, while jobs of the first have no
    NAME.rc yet; ``FORCE=1`` starts beside them; once they have ended it starts and adds its runs to the batch."""
    import subprocess

    script = DEVICE_BATCH
    env = _fake_gpu_machine(tmp_path, 1, "exit 0")
    batch = tmp_path / "runs" / "batch"
    batch.mkdir(parents=True)
    (batch / "commands.txt").write_text("first (GPU 0): --task cartpole-balance\n"
                                        "done (GPU 0): --task cartpole-balance\n")
    (batch / "done.rc").write_text("0\n")  # ended; "first" still runs
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("second  --task cartpole-balance\n")
    start = lambda **extra: subprocess.run(["bash", script, "start", str(jobs), "60", "0"], capture_output=True,
                                           text=True, timeout=60, env={**env, **extra}, cwd=tmp_path)
    refused = start()
    assert refused.returncode == 2 and "jobs of an earlier start still run" in refused.stderr
    assert "first ;" in refused.stderr and "done" not in refused.stderr
    assert not (batch / "second.log").exists()
    assert start(FORCE="1").returncode == 0 and (batch / "second.log").exists()
    (batch / "first.rc").write_text("0\n")
    (batch / "second.rc").write_text("0\n")
    jobs.write_text("third  --task cartpole-balance\n")
    assert start().returncode == 0
    names = [line.split(" ")[0] for line in (batch / "commands.txt").read_text().splitlines()]
    assert names == ["first", "done", "second", "third"]


def _launched_before(tmp_path):
    """A batch whose earlier start launched the job "cut" (its command and the first launch's log, no exit status
    yet) and a jobs file that starts it again: (the batch folder, the jobs file)."""
    batch = tmp_path / "runs" / "batch"
    batch.mkdir(parents=True)
    (batch / "commands.txt").write_text("cut (GPU 0): --task cartpole-balance\n")
    (batch / "cut.log").write_text("first launch\n")
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("cut  --task cartpole-balance\n")
    return batch, jobs


def test_device_batch_relaunch_waits_for_the_earlier_process_of_its_job(tmp_path):
    """Starting a job again (a run cut by its timeout, resumed from its checkpoint) waits for its earlier launch
    to end, at most RELAUNCH_WAIT seconds, then refuses naming it (other running jobs need no FORCE for that);
    once it has ended it relaunches: the earlier wall seconds kept, the log appended, the exit status renewed."""
    import subprocess
    import time

    env = _fake_gpu_machine(tmp_path, 1, "echo launched; exit 0")
    batch, jobs = _launched_before(tmp_path)
    start = lambda: subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "20"], capture_output=True,
                                   text=True, timeout=60, env={**env, "RELAUNCH_WAIT": "0"}, cwd=tmp_path)
    refused = start()  # no cut.rc: the earlier process still runs
    assert refused.returncode == 2, refused.stderr
    assert "cut: its earlier launch still runs after 0 s" in refused.stderr and "not relaunched" in refused.stderr
    assert (batch / "commands.txt").read_text().count("cut (GPU 0)") == 1
    (batch / "cut.rc").write_text("124\n")  # ended by its timeout, checkpoint written
    (batch / "cut.seconds").write_text("590.5\n")
    relaunched = start()
    assert relaunched.returncode == 0, relaunched.stderr
    assert (batch / "cut.earlier-seconds").read_text() == "590.5\n"
    deadline = time.monotonic() + 20  # the relaunched job runs in the background: its exit status, when written
    while not (batch / "cut.rc").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (batch / "cut.rc").read_text().strip() == "0" and float((batch / "cut.seconds").read_text()) < 60
    assert (batch / "cut.log").read_text() == "first launch\nlaunched\n"
    assert "earlier launches: 590.5 s" in relaunched.stdout


def test_device_batch_does_not_relaunch_a_run_that_reached_its_steps(tmp_path):
    """A training job whose earlier launch of the same line exited 0 is reported and not launched again (its run
    would only resume and exit), and the GPU's memory goes to the jobs that do launch; a job that was cut (exit
    124), a changed line, a study line or RERUN=1 launches as before."""
    import subprocess
    import time

    env = _fake_gpu_machine(tmp_path, 1, 'echo "launched mem=$XLA_PYTHON_CLIENT_MEM_FRACTION"; exit 0')
    batch = tmp_path / "runs" / "batch"
    batch.mkdir(parents=True)
    (batch / "commands.txt").write_text("done (GPU 0): --task cartpole-balance\ncut (GPU 0): --task cartpole-balance\n"
                                        "study (GPU 0): experiment fig5_19 --small\n")
    for name, rc in (("done", 0), ("cut", 124), ("study", 0)):
        (batch / f"{name}.rc").write_text(f"{rc}\n")
        (batch / f"{name}.log").write_text("first launch\n")
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("done@0  --task cartpole-balance\ncut@0  --task cartpole-balance\n")

    def start(**extra):  # a start, returned once every job it launched (in the background) has its exit status
        result = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "20"], capture_output=True,
                                text=True, timeout=60, env={**env, **extra}, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        deadline = time.monotonic() + 20
        while not all((batch / f"{n}.rc").exists() for n in ("done", "cut", "study")):
            assert time.monotonic() < deadline, "a launched job wrote no exit status"
            time.sleep(0.05)
        return result

    first = start()
    assert "done: ended (exit 0) at an earlier launch of this line: not launched again" in first.stdout
    assert (batch / "done.log").read_text() == "first launch\n" and (batch / "done.rc").read_text() == "0\n"
    assert (batch / "cut.log").read_text() == "first launch\nlaunched mem=0.9\n"  # the GPU is the cut run's alone
    launched = [line.split(" (")[0] for line in (batch / "commands.txt").read_text().splitlines()]
    assert launched == ["done", "cut", "study", "cut"]
    jobs.write_text("study  experiment fig5_19 --small\n")  # a study's exit status says nothing of its training
    start()
    assert (batch / "study.log").read_text().endswith("launched mem=0.9\n")
    jobs.write_text("done  --task cartpole-balance --steps 400000\n")  # another line under the same name
    start()
    assert (batch / "done.log").read_text() == "first launch\nlaunched mem=0.9\n"
    start(RERUN="1")  # the same line again, relaunched on request
    assert (batch / "done.log").read_text().count("launched") == 2


def test_device_batch_stops_a_job_at_its_limit_unless_extend_moves_it(tmp_path):
    """Each job gets SIGTERM once its SECONDS have passed and then records exit 124, as under ``timeout -s TERM``
    (a training run saves a checkpoint and exits 0 on it); ``extend SECONDS NAME`` moves a running job's limit,
    so that job runs past the first limit to its own end (exit 0); the report gives a running job's time left.
    Bad seconds, a job that is not running and a batch with nothing running are refused, naming why."""
    import subprocess
    import time

    body = ('trap \'echo termed; exit 0\' TERM; '  # the trainer's SIGTERM: checkpoint, exit 0
            'end=$(($(date +%s) + 20)); case "$*" in *runs/batch/kept*) end=$(($(date +%s) + 3));; esac; '
            'while [ "$(date +%s)" -lt "$end" ]; do sleep 0.05; done; echo reached its end')
    env = _fake_gpu_machine(tmp_path, 1, body, DEADLINE_POLL="0.05")
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("kept  --task cartpole-balance\ncut  --task cartpole-balance\n")
    run = lambda *args: subprocess.run(["bash", DEVICE_BATCH, *args], capture_output=True, text=True, timeout=60,
                                       env=env, cwd=tmp_path)
    batch = tmp_path / "runs" / "batch"
    assert run("start", str(jobs), "2", "0").returncode == 0  # both stopped ~2 s after their launch ...
    moved = run("extend", "30", "kept")  # ... unless moved: kept's limit 30 s later, cut's as it was
    assert moved.returncode == 0, moved.stderr
    assert moved.stdout.startswith("kept: limit moved by 30 s: SIGTERM in ") and "cut" not in moved.stdout
    assert 29 <= int(moved.stdout.split("SIGTERM in ")[1].split()[0]) <= 32
    report = run("wait", "0").stdout
    assert "running: SIGTERM in " in report and "unless extended" in report
    refused = run("extend", "ten")
    assert refused.returncode == 2 and "SECONDS must be a whole number of seconds (negative: sooner), not 'ten'" in (
        refused.stderr)
    refused = run("extend", "5", "nope")
    assert refused.returncode == 2 and "'nope' is no running job (running: kept cut )" in refused.stderr
    deadline = time.monotonic() + 30
    while not all((batch / f"{n}.rc").exists() for n in ("kept", "cut")) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (batch / "cut.rc").read_text() == "124\n" and (batch / "cut.log").read_text() == "termed\n"
    assert (batch / "kept.rc").read_text() == "0\n" and (batch / "kept.log").read_text() == "reached its end\n"
    assert float((batch / "kept.seconds").read_text()) >= 2.0  # past the first limit
    refused = run("extend", "5")
    assert refused.returncode == 2 and "no job of this machine's batch is running" in refused.stderr
    refused = run("start", str(jobs), "1.5", "0")  # not a whole number of seconds: nothing launched
    assert refused.returncode == 2 and "SECONDS must be a whole number of seconds, not '1.5'" in refused.stderr
    assert (batch / "commands.txt").read_text().count("kept (GPU 0)") == 1


def test_device_batch_report_keeps_its_deadline_and_packs_out_while_it_waits(tmp_path):
    """``start``'s REPORT counts from the start itself (a relaunch's wait for its earlier process included), and
    while a report waits it packs report.txt and results.tar.gz into $OUT every SNAPSHOT_EVERY seconds, so that a
    device call cut at its limit still brings back the batch's state."""
    import subprocess
    import tarfile
    import threading
    import time

    out = tmp_path / "out"
    out.mkdir()
    env = _fake_gpu_machine(tmp_path, 1, "echo launched; sleep 8", OUT=str(out), SNAPSHOT_EVERY="1",
                            RELAUNCH_WAIT="30")
    batch, jobs = _launched_before(tmp_path)
    ended = threading.Timer(1.0, lambda: (batch / "cut.rc").write_text("124\n"))  # the earlier process ends
    ended.start()
    begun = time.monotonic()
    started = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "3"], capture_output=True, text=True,
                             timeout=60, env=env, cwd=tmp_path)
    took = time.monotonic() - begun
    ended.join()
    assert started.returncode == 0, started.stderr
    # the wait for the earlier process (polled every 2 s) ends at ~2 s, the report at ~3 s (not ~2 + 3)
    assert 2.0 <= took < 4.7, took
    assert (out / "report.txt").read_text() in started.stdout and "cut " in (out / "report.txt").read_text()
    for name in ("report.txt", "results.tar.gz"):
        (out / name).unlink()
    waiting = subprocess.Popen(["bash", DEVICE_BATCH, "wait", "50"], stdout=subprocess.DEVNULL, env=env,
                               cwd=tmp_path)
    try:
        deadline = time.monotonic() + 20
        while not (out / "results.tar.gz").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert waiting.poll() is None  # still waiting for the run (it sleeps 8 s), yet packed already
        with tarfile.open(out / "results.tar.gz") as tar:
            assert "./cut.log" in tar.getnames()
        assert "=== " in (out / "report.txt").read_text()
    finally:
        waiting.kill()
        waiting.wait()


def test_device_batch_packs_policies_apart_and_under_their_limit(tmp_path):
    """The runs' policy.npz files travel in $OUT/policies.tar, not in results.tar.gz, oldest run first while they
    keep under POLICY_MIB, then the evaluations' policies; a file that would pass it is left out and named in the
    report, later ones still fit."""
    import subprocess
    import tarfile

    out = tmp_path / "out"
    out.mkdir()
    body = ('while [ $# -gt 0 ]; do case $1 in --out) run=$2;; --size) size=$2;; esac; shift; done; '
            'mkdir -p "$run/checkpoints"; echo rows >"$run/eval.csv"; head -c "$size" /dev/zero >"$run/policy.npz"; '
            'head -c 10 /dev/zero >"$run/checkpoints/policy.npz"; mkdir -p "$run/policies"; '
            'for step in 600 1200; do head -c 100 /dev/zero >"$run/policies/policy-$step.npz"; done')
    env = _fake_gpu_machine(tmp_path, 1, body, OUT=str(out), POLICY_MIB="1")
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("a --size 400000\nb --size 800000\nc --size 400000\n")  # a fits, a + b do not, a + c do
    result = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "30"], capture_output=True,
                            text=True, timeout=60, env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    with tarfile.open(out / "policies.tar") as tar:  # then the evaluations' policies (--eval-policies), newest first
        assert tar.getnames() == ["./a/policy.npz", "./c/policy.npz",
                                  *(f"./{run}/policies/policy-{step}.npz" for run in "abc" for step in (1200, 600))]
        assert tar.getmember("./a/policy.npz").size == 400_000
    with tarfile.open(out / "results.tar.gz") as tar:
        names = tar.getnames()
    assert "./a/eval.csv" in names and not [n for n in names if "policy" in n or "checkpoints" in n]
    report = (out / "report.txt").read_text()
    assert "policy left out of policies.tar (over POLICY_MIB=1): ./b/policy.npz" in report
    assert report.count("left out") == 1


def test_ingest_batch_files_study_runs_ranks_and_whole_tables(tmp_path):
    """``ingest_batch.sh``: a device batch's results.tar.gz becomes study-runs/ folders, their effective-rank
    figures and every agent's row of the study's table (the job line's --agents dropped)."""
    import json
    import subprocess
    import sys
    import tarfile

    batch = tmp_path / "batch"
    run_dir = batch / "experiments" / "acrobot-swingup" / "tdmpc2" / "noise0.1-seeds1"
    _fake_run(str(run_dir), 50_000, checkpoint=False, returns=[[10.0, 30.0]], eval_name="mjx-noise0.1-50000.csv")
    (run_dir / "config.json").write_text(json.dumps({"config": {"task": "acrobot-swingup", "agent": "tdmpc2"},
                                                     "agent_config": {"model": {"latent_dim": 8}}}))
    _write(str(run_dir / "eval.csv"), [{"env_step": 50_000, "seed": 0, "episode": e, "return": 1.0,
                                        "effective_rank": rank} for e, rank in enumerate((3.0, 5.0))])
    (batch / "plain-run").mkdir()
    (batch / "plain-run" / "config.json").write_text("{}")
    (batch / "commands.txt").write_text("t55 (GPU 0): experiment table5_5 --agents tdmpc2 --seeds 1 --steps 50000\n")
    with tarfile.open(tmp_path / "results.tar.gz", "w:gz") as tar:
        tar.add(batch, arcname=".")
    (run_dir / "policy.npz").write_bytes(b"study policy")  # packed apart, as device_batch.sh does
    (batch / "plain-run" / "policy.npz").write_bytes(b"plain policy")
    (batch / "plain-run" / "policies").mkdir()
    (batch / "plain-run" / "policies" / "policy-600.npz").write_bytes(b"policy at 600")  # --eval-policies
    with tarfile.open(tmp_path / "policies.tar", "w") as tar:
        for path in (run_dir / "policy.npz", batch / "plain-run" / "policy.npz",
                     batch / "plain-run" / "policies" / "policy-600.npz"):
            tar.add(path, arcname="./" + str(path.relative_to(batch)))
    work = tmp_path / "work"
    work.mkdir()
    script = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "ingest_batch.sh")
    result = subprocess.run(["bash", script, str(tmp_path / "results.tar.gz")], capture_output=True, text=True,
                            timeout=300, cwd=work,
                            env={**os.environ, "PYTHON": sys.executable, "JAX_PLATFORMS": "cpu"})
    assert result.returncode == 0, result.stderr
    filed = work / "experiments" / "results" / "study-runs" / "acrobot-swingup" / "tdmpc2" / "noise0.1-seeds1"
    with open(filed / "analysis" / "effective_rank.csv", newline="") as f:
        ranks = list(csv.DictReader(f))
    assert [(r["env_step"], float(r["effective_rank"]), r["latent_dim"]) for r in ranks] == [("50000", 4.0, "8")]
    table = (work / "experiments" / "results" / "studies" / "table5_5.md").read_text()
    assert "| acrobot-swingup | noise0.1 | noise0.1 | tdmpc2 | 50,000 | 1 × 2 | 20.0 ± 10.0 |" in table
    assert table.count("| cfc-zp-det | not yet run |") == 3 and table.count("not yet run") == 6 * 3 + 2
    assert "plain run (file it by hand): runs/batch/plain-run, copied to runs/ingested/plain-run" in result.stdout
    assert (work / "runs" / "ingested" / "plain-run" / "config.json").read_text() == "{}"
    assert f"policies 2 policy.npz from {tmp_path / 'policies.tar'}" in result.stdout  # each beside its run
    assert (filed / "policy.npz").read_bytes() == b"study policy"
    assert (work / "runs" / "ingested" / "plain-run" / "policy.npz").read_bytes() == b"plain policy"
    assert "1 evaluations' policies (policies/policy-<step>.npz)" in result.stdout
    assert (work / "runs" / "ingested" / "plain-run" / "policies" / "policy-600.npz").read_bytes() == b"policy at 600"
    assert "(no table for plain-run)" in result.stdout  # its config.json is no trainer's: said, not fatal
    assert "(no speed table)" in result.stdout and "(no commands)" in result.stdout


def test_ingest_batch_keeps_a_runs_earlier_policies_that_a_later_batch_left_out(tmp_path):
    """A warm machine's second batch brings a run of its first back again, its policies.tar without the
    evaluations' policies it had no room for: the staged run keeps those of the first ingest. A run of the same
    name with another config.json (launched again) keeps nothing of the older one."""
    import subprocess
    import tarfile

    def ingest(name: str, config: str, policies: dict[str, bytes]) -> subprocess.CompletedProcess:
        batch = tmp_path / name / "batch"
        run = batch / "acro"
        (run / "policies").mkdir(parents=True)
        (run / "config.json").write_text(config)
        for rel, data in policies.items():
            (run / rel).write_bytes(data)
        with tarfile.open(tmp_path / name / "policies.tar", "w") as tar:
            for rel in policies:
                tar.add(run / rel, arcname=f"./acro/{rel}")
            for rel in policies:
                (run / rel).unlink()
        with tarfile.open(tmp_path / name / "results.tar.gz", "w:gz") as tar:
            tar.add(batch, arcname=".")
        return subprocess.run(["bash", script, str(tmp_path / name / "results.tar.gz")], cwd=work, timeout=120,
                              env={**os.environ, "PYTHON": "true"}, capture_output=True, text=True)  # no tables

    script = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "ingest_batch.sh")
    work = tmp_path / "work"
    work.mkdir()
    staged = work / "runs" / "ingested" / "acro"
    first = ingest("first", '{"launch": 1}', {"policy.npz": b"final", "policies/policy-600.npz": b"at 600",
                                              "policies/policy-1200.npz": b"at 1200"})
    assert first.returncode == 0, first.stderr
    second = ingest("second", '{"launch": 1}', {"policies/policy-1200.npz": b"at 1200"})
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in (staged / "policies").iterdir()) == ["policy-1200.npz", "policy-600.npz"]
    assert (staged / "policy.npz").read_bytes() == b"final"
    assert (staged / "policies" / "policy-600.npz").read_bytes() == b"at 600"
    assert "kept     runs/ingested/acro/policies/policy-600.npz" in second.stdout
    assert second.stdout.count("kept ") == 2
    relaunched = ingest("third", '{"launch": 2}', {"policies/policy-1200.npz": b"new at 1200"})
    assert relaunched.returncode == 0, relaunched.stderr
    assert [p.name for p in (staged / "policies").iterdir()] == ["policy-1200.npz"]
    assert not (staged / "policy.npz").exists() and "kept " not in relaunched.stdout


def test_ingest_batch_never_replaces_a_longer_filed_run_with_a_shorter_copy(tmp_path):
    """A run killed early on the device (fewer env steps than the copy filed before) is kept out of study-runs/
    unless FORCE=1; a copy that reached as far or further replaces the filed one, listing the filed copy's
    evaluation files it drops; a new folder is always filed."""
    import subprocess
    import sys
    import tarfile

    def batch_tar(name, runs):
        batch = tmp_path / name
        for rel, last in runs.items():
            _fake_run(str(batch / "experiments" / rel), last, checkpoint=False)
        with tarfile.open(tmp_path / f"{name}.tar.gz", "w:gz") as tar:
            tar.add(batch, arcname=".")
        return str(tmp_path / f"{name}.tar.gz")

    def last_step(rel):
        with open(work / "experiments" / "results" / "study-runs" / rel / "eval.csv", newline="") as f:
            return max(int(row["env_step"]) for row in csv.DictReader(f))

    work = tmp_path / "work"
    work.mkdir()
    script = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "ingest_batch.sh")
    env = {**os.environ, "PYTHON": sys.executable, "JAX_PLATFORMS": "cpu"}
    long_run, other = "acrobot-swingup/cfc-zp-det/clean-seeds3-envs8", "cartpole-swingup/tdmpc2/clean-seeds3-envs8"
    first = batch_tar("first", {long_run: 164_688})
    assert subprocess.run(["bash", script, first], cwd=work, env=env, timeout=120).returncode == 0
    shorter = batch_tar("shorter", {long_run: 20_976, other: 40_000})
    result = subprocess.run(["bash", script, shorter], cwd=work, env=env, timeout=120, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "kept     experiments/results/study-runs/" + long_run in result.stdout
    assert (last_step(long_run), last_step(other)) == (164_688, 40_000)
    forced = subprocess.run(["bash", script, shorter], cwd=work, env={**env, "FORCE": "1"}, timeout=120)
    assert forced.returncode == 0 and last_step(long_run) == 20_976
    filed_evals = work / "experiments" / "results" / "study-runs" / long_run / "evals"
    filed_evals.mkdir()
    (filed_evals / "horizon10-clean-20976.csv").write_text("env_step,seed,episode,return\n20976,0,0,1.0\n")
    longer = batch_tar("longer", {long_run: 212_592})
    result = subprocess.run(["bash", script, longer], cwd=work, env=env, timeout=120, capture_output=True, text=True)
    assert result.returncode == 0 and last_step(long_run) == 212_592, result.stderr
    assert f"dropped  experiments/results/study-runs/{long_run}/evals/horizon10-clean-20976.csv" in result.stdout
    assert not filed_evals.exists() and result.stdout.count("dropped") == 1


def test_throughput_ab_runs_each_snapshot_with_its_own_package(tmp_path):
    """``throughput_ab.sh NAME args`` runs runs/gpu-old's then runs/gpu-head's train_throughput.py, each with its
    own src/ after $SITE on PYTHONPATH, the same arguments and an --out per version; a missing snapshot stops it
    with its name."""
    import subprocess

    script = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "throughput_ab.sh")
    fake = ("import os, sys\n"
            "line = os.environ['PYTHONPATH'] + ' | ' + ' '.join(sys.argv[1:])\n"
            "open(os.environ['LOG'], 'a').write(line + '\\n')\n")
    for version in ("old", "head"):
        (tmp_path / "runs" / f"gpu-{version}" / "benchmarks").mkdir(parents=True)
        (tmp_path / "runs" / f"gpu-{version}" / "benchmarks" / "train_throughput.py").write_text(fake)
    log = tmp_path / "log.txt"
    env = {**os.environ, "LOG": str(log), "OUT": "/out", "SITE": "/site"}
    result = subprocess.run(["bash", script, "run9", "--tasks", "cartpole-swingup", "--seeds", "1,8"], cwd=tmp_path,
                            env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    lines = log.read_text().splitlines()
    assert lines == [f"/site:{tmp_path}/runs/gpu-{v}/src | --tasks cartpole-swingup --seeds 1,8 --out "
                     f"/out/{{device}}-run9-{v}.json" for v in ("old", "head")]
    result = subprocess.run(["bash", script, "run9"], cwd=tmp_path, env={**env, "VERSIONS": "new"},
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and "runs/gpu-new holds no snapshot" in result.stderr


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
    _fake_run(noisy, 200_016, returns=[[300.0, 400.0], [500.0, 600.0]],
              eval_name="mjx-flicker0.2-noise0.2-200016.csv")
    _write(os.path.join(noisy, "evals", "mjx-flicker0.2-noise0.2-100000.csv"),
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
    _write(os.path.join(folder, "evals", "horizon3-clean-200016.csv"),
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
    _fake_run(folder, 164_688, returns=[[700.0, 900.0]], eval_name="horizon10-clean-164688.csv")
    _write(os.path.join(folder, "evals", "horizon3-clean-184688.csv"),
           [{"env_step": 184_688, "seed": 0, "episode": 0, "return": 1.0}])
    row = next(r for r in study_rows(study, [spec], options.steps) if r["task"] == "acrobot-swingup")
    assert row["mean"] == ""  # the run does not say which horizon it was trained with
    with open(os.path.join(folder, "config.json"), "w") as f:
        f.write('{"config": {}, "agent_config": {"planner": {"horizon": 10}}}')
    row = study_rows(study, [spec], options.steps)[0]
    assert (row["env_step"], row["mean"], row["status"]) == (164_688, 800.0, "partial")
    _write(os.path.join(folder, "evals", "mjx-clean-164688.csv"),
           [{"env_step": 164_688, "seed": 0, "episode": 0, "return": 5.0}])
    assert study_rows(study, [spec], options.steps)[0]["mean"] == 5.0  # a tie: the plain file
    _write(os.path.join(folder, "evals", "mjx-clean-184688.csv"),
           [{"env_step": 184_688, "seed": 0, "episode": 0, "return": 6.0}])
    assert study_rows(study, [spec], options.steps)[0]["env_step"] == 184_688
    assert study_rows(study, [spec], options.steps, backend="dm_control")[0]["mean"] == ""


def _fake_noise_evals(folder, step, means):
    """Evaluation files of a run at σ = 0.1, 0.2, 0.3 (2 seeds × 2 episodes, returns mean ± 10)."""
    for sigma, mean in zip((0.1, 0.2, 0.3), means, strict=True):
        _write(os.path.join(folder, "evals", f"mjx-noise{sigma:g}-{step}.csv"),
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
    _fake_run(specs[1].folder, 40_000)  # cfc-zp-det, stopped at 40K
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
    _fake_run(specs[0].folder, 50_016, returns=[[190.0, 210.0]], eval_name="mjx-novel-50016.csv")
    conditions, series = figures.bar_series(study_rows(grid.get_study("table5_4"), specs, options.steps))
    assert conditions == [("cartpole-swingup", "novel")]
    assert series == {"tdmpc2": {"mean": [200.0], "std": [10.0], "thesis": [193.22], "env_step": [50_016]}}


def test_horizon_figure_reads_every_episode(tmp_path):
    from lnnmpc.experiments import figures

    options = grid.GridOptions(runs_dir=str(tmp_path), steps=50_000, seeds=1)
    specs = grid.expand(grid.get_study("fig5_19"), options)
    _fake_run(specs[0].folder, 50_016)
    for h in (1, 10):
        _write(grid.eval_file(specs[0].folder, 50_016, "", horizon=h),
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
