"""``experiments/scripts/file_final_evals.sh``: a final_evals.sh tarball filed into a results folder under the names
the results READMEs read (the prefix dropped, the checkpoint's step added, dm_control's marked as the device's),
with nothing overwritten and nothing half filed."""

import io
import os
import subprocess
import tarfile

import pytest

FILE_FINAL_EVALS = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "file_final_evals.sh")
HEADER = "env_step,seed,episode,return,backend,obs,actor,planner,eval_seed"


def _csv(step, returns, backend="mjx", steps=None):
    steps = steps or [step] * len(returns)
    rows = [f"{s},0,{i},{r},{backend},clean,planner,,0" for i, (s, r) in enumerate(zip(steps, returns, strict=True))]
    return "\n".join([HEADER, *rows]) + "\n"


def _tarball(path, files):
    """``files``: {name under runs/batch/: text}, packed as final_evals.sh packs them."""
    with tarfile.open(path, "w:gz") as tar:
        for name, text in files.items():
            data = text.encode()
            info = tarfile.TarInfo(f"runs/batch/{name}")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


def _run(*args, **extra):
    return subprocess.run(["bash", FILE_FINAL_EVALS, *map(str, args)], capture_output=True, text=True, timeout=60,
                          env={**os.environ, **extra})


def _two_runs():
    files = {}
    for seed, base in ((1, 500.0), (4, 600.0)):
        name = f"acrobot-recipe-floor-seed{seed}"
        files[f"mjx-20ep-{name}.csv"] = _csv(200256, [base, base + 10])
        files[f"eval-{name}.log"] = f"mjx log {seed}\n"
        files[f"dm_control-{name}.csv"] = _csv(200256, [base + 1, base + 2, base + 6], backend="dm_control")
        files[f"dm_control-{name}.log"] = f"dm_control log {seed}\n"
    return files


def test_files_both_measures_of_each_run_under_the_readmes_names(tmp_path):
    files = _two_runs()
    folder = tmp_path / "results"
    folder.mkdir()
    done = _run(_tarball(tmp_path / "final-evals.tar.gz", files), folder)
    assert (done.returncode, done.stderr) == (0, "")
    analysis = folder / "analysis"
    expected = {}
    for seed in (1, 4):
        name = f"acrobot-recipe-floor-seed{seed}"
        expected.update({
            f"mjx-20ep-floor-seed{seed}-200256.csv": files[f"mjx-20ep-{name}.csv"],
            f"logs/mjx-20ep-floor-seed{seed}.log": files[f"eval-{name}.log"],
            f"dm_control-gpu-floor-seed{seed}-200256.csv": files[f"dm_control-{name}.csv"],
            f"logs/dm_control-gpu-floor-seed{seed}.log": files[f"dm_control-{name}.log"]})
    filed = {str(p.relative_to(analysis)): p.read_text() for p in analysis.rglob("*") if p.is_file()}
    assert filed == expected
    csvs = {"mjx-20ep-floor-seed1-200256.csv": (2, "505.0"), "dm_control-gpu-floor-seed1-200256.csv": (3, "503.0"),
            "mjx-20ep-floor-seed4-200256.csv": (2, "605.0"), "dm_control-gpu-floor-seed4-200256.csv": (3, "603.0")}
    logs = [f"logs/{kind}-floor-seed{seed}.log" for seed in (1, 4) for kind in ("mjx-20ep", "dm_control-gpu")]
    assert sorted(done.stdout.splitlines()) == sorted(
        [f"filed {analysis / name} ({n} episodes, mean return {mean})" for name, (n, mean) in csvs.items()]
        + [f"filed {analysis / name}" for name in logs])
    # another prefix (here none): the run's whole name
    other = tmp_path / "other"
    other.mkdir()
    assert _run(tmp_path / "final-evals.tar.gz", other, "").returncode == 0
    assert (other / "analysis" / "mjx-20ep-acrobot-recipe-floor-seed4-200256.csv").read_text() == \
        files["mjx-20ep-acrobot-recipe-floor-seed4.csv"]


def test_a_failed_evaluations_log_is_filed_as_failed(tmp_path):
    files = {"mjx-20ep-acrobot-recipe-x-seed2.csv": _csv(40000, [1.5]), "eval-acrobot-recipe-x-seed2.log": "ok\n",
             "dm_control-acrobot-recipe-x-seed2.log": "Error: dm_control failed\n"}
    folder = tmp_path / "results"
    folder.mkdir()
    done = _run(_tarball(tmp_path / "t.tar.gz", files), folder)
    assert done.returncode == 0, done.stderr
    assert sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()) == [
        "analysis/logs/dm_control-gpu-failed-x-seed2.log", "analysis/logs/mjx-20ep-x-seed2.log",
        "analysis/mjx-20ep-x-seed2-40000.csv"]
    assert (folder / "analysis/logs/dm_control-gpu-failed-x-seed2.log").read_text() == "Error: dm_control failed\n"


def test_refuses_to_overwrite_and_files_nothing_unless_forced(tmp_path):
    tarball = _tarball(tmp_path / "t.tar.gz", _two_runs())
    folder = tmp_path / "results"
    (folder / "analysis").mkdir(parents=True)
    taken = folder / "analysis" / "dm_control-gpu-floor-seed4-200256.csv"
    taken.write_text("filed before\n")
    done = _run(tarball, folder)
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr == f"{taken} exists (FORCE=1 replaces it)\nnothing filed\n"
    assert os.listdir(folder / "analysis") == [taken.name] and taken.read_text() == "filed before\n"
    forced = _run(tarball, folder, FORCE="1")
    assert forced.returncode == 0, forced.stderr
    assert taken.read_text() == _two_runs()["dm_control-acrobot-recipe-floor-seed4.csv"]
    assert len(list((folder / "analysis").rglob("*.csv"))) == 4


@pytest.mark.parametrize("text,reason", [
    (_csv(0, [1.0, 2.0], steps=[40000, 80000]), "its rows name 2 env steps, not one"),
    (HEADER + "\n", "its rows name 0 env steps, not one"),
    ("episode,return\n0,1.5\n", "its first column is not env_step (not a cli eval CSV)")])
def test_refuses_a_csv_without_one_step_and_files_nothing(tmp_path, text, reason):
    files = {**_two_runs(), "mjx-20ep-acrobot-recipe-bad-seed0.csv": text}
    folder = tmp_path / "results"
    folder.mkdir()
    done = _run(_tarball(tmp_path / "t.tar.gz", files), folder)
    assert (done.returncode, done.stdout) == (1, "")
    assert done.stderr == f"mjx-20ep-acrobot-recipe-bad-seed0.csv: {reason}\nnothing filed\n"
    assert os.listdir(folder) == []


def test_bad_arguments_exit_2_naming_what_is_wrong(tmp_path):
    usage = "usage: file_final_evals.sh TARBALL FOLDER [PREFIX]\n"
    bare = _run()
    assert (bare.returncode, bare.stderr) == (2, usage)
    assert _run("a", "b", "c", "d").stderr == usage
    missing = _run(tmp_path / "gone.tar.gz", tmp_path)
    assert (missing.returncode, missing.stderr) == (
        2, f"{tmp_path}/gone.tar.gz: no such file (final_evals.sh packs $OUT/final-evals.tar.gz)\n")
    tarball = _tarball(tmp_path / "t.tar.gz", _two_runs())
    no_folder = _run(tarball, tmp_path / "nowhere")
    assert (no_folder.returncode, no_folder.stderr) == (
        2, f"{tmp_path}/nowhere: no such folder (the results folder the runs were filed in)\n")
    (tmp_path / "plain.txt").write_text("not a tarball")
    assert _run(tmp_path / "plain.txt", tmp_path).stderr.endswith("not a tar.gz archive\n")
    with tarfile.open(tmp_path / "other.tar.gz", "w:gz") as tar:
        tar.add(tmp_path / "plain.txt", arcname="plain.txt")
    other = _run(tmp_path / "other.tar.gz", tmp_path)
    assert (other.returncode, other.stderr) == (
        2, f"{tmp_path}/other.tar.gz holds no runs/batch/ folder: not a final_evals.sh tarball\n")
