"""A run's provenance (lnnmpc.train.provenance): the git state of the code, the command line, the summary line."""

import os
import subprocess

import pytest

from lnnmpc.train import provenance


def _git(repo, *args):
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout.strip()


def test_git_state_names_the_commit_and_whether_tracked_files_changed(tmp_path):
    repo = tmp_path / "repo"
    (repo / "pkg").mkdir(parents=True)
    _git(repo, "init", "-q")
    (repo / "pkg" / "a.py").write_text("x = 1\n")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "one")
    head = _git(repo, "rev-parse", "HEAD")
    assert provenance.git_state(str(repo / "pkg")) == {"commit": head, "dirty": False}
    (repo / "pkg" / "new.py").write_text("untracked\n")  # untracked files do not count
    assert provenance.git_state(str(repo / "pkg")) == {"commit": head, "dirty": False}
    (repo / "pkg" / "a.py").write_text("x = 2\n")
    assert provenance.git_state(str(repo / "pkg")) == {"commit": head, "dirty": True}


def test_git_state_outside_a_checkout_is_none(tmp_path, monkeypatch):
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path))  # do not find a repository above tmp_path
    assert provenance.git_state(str(tmp_path)) == {"commit": None, "dirty": None}


def test_git_state_of_a_snapshot_is_its_commit_file_and_of_an_ignored_copy_none(tmp_path):
    """Code unpacked under a checkout's ignored folder (a device batch's ``runs/gpu-head``) is not that
    checkout's HEAD: without a SNAPSHOT_COMMIT file it records none, with one (``snapshot.sh``) that commit."""
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    (repo / ".gitignore").write_text("runs/\n")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "one")
    package = repo / "runs" / "gpu-head" / "src" / "lnnmpc"
    package.mkdir(parents=True)
    assert provenance.git_state(str(package)) == {"commit": None, "dirty": None}
    (repo / "runs" / "gpu-head" / "SNAPSHOT_COMMIT").write_text("abc123\n")
    state = provenance.git_state(str(package))
    assert state == {"commit": "abc123", "dirty": False, "snapshot": str(repo / "runs" / "gpu-head")}
    assert provenance.code_line([{"git": state}]) == "abc123 (snapshot)"


def test_snapshot_script_freezes_head_and_refuses_uncommitted_code(tmp_path):
    script = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "snapshot.sh")
    repo = tmp_path / "repo"
    (repo / "src" / "lnnmpc").mkdir(parents=True)
    (repo / "benchmarks").mkdir()
    _git(repo, "init", "-q")
    (repo / "src" / "lnnmpc" / "a.py").write_text("x = 1\n")
    (repo / "benchmarks" / "b.py").write_text("y = 1\n")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "one")
    head = _git(repo, "rev-parse", "HEAD")
    env = {k: v for k, v in os.environ.items() if k != "FORCE"}
    run = lambda: subprocess.run(["bash", script, "snap"], cwd=repo, capture_output=True, text=True, env=env)
    done = run()
    assert done.returncode == 0, done.stderr
    assert (repo / "snap" / "SNAPSHOT_COMMIT").read_text().strip() == head
    assert (repo / "snap" / "src" / "lnnmpc" / "a.py").read_text() == "x = 1\n"
    assert provenance.git_state(str(repo / "snap" / "src" / "lnnmpc"))["commit"] == head
    (repo / "src" / "lnnmpc" / "a.py").write_text("x = 2\n")
    refused = run()
    assert refused.returncode == 1 and "commit them first" in refused.stderr
    assert (repo / "snap" / "src" / "lnnmpc" / "a.py").read_text() == "x = 1\n"  # the old snapshot is kept


def test_command_line_names_package_scripts_as_modules_and_quotes_arguments():
    root = os.path.dirname(provenance.__file__)
    assert (provenance.command_line([os.path.join(root, "cli.py"), "train", "--obs", "noise=0.1, flicker=0.2"])
            == "python -m lnnmpc.train.cli train --obs 'noise=0.1, flicker=0.2'")
    assert provenance.command_line(["/usr/bin/pytest", "-q"]) == "/usr/bin/pytest -q"
    assert provenance.command_line([]) == ""


@pytest.mark.parametrize("entries, expected", [
    ([], "not recorded"),
    ([{"git": {"commit": "a" * 40, "dirty": False}, "versions": {"jax": "0.11.2", "mujoco-mjx": "3.17.0"}}],
     "aaaaaaaaaaaa; jax 0.11.2, mujoco-mjx 3.17.0"),
    ([{"git": {"commit": None, "dirty": None}, "versions": {"jax": "0.11.2"}}] * 2,
     "not a git checkout; jax 0.11.2; 2 starts (resumed)"),
    ([{"git": {"commit": "b" * 40, "dirty": True}, "versions": {}}], "bbbbbbbbbbbb (uncommitted changes)"),
])
def test_code_line_summarises_the_newest_start(entries, expected):
    assert provenance.code_line(entries) == expected


def test_provenance_entry_records_the_installed_versions():
    from importlib import metadata

    entry = provenance.provenance_entry(["prog", "--flag"])
    assert entry["argv"] == ["prog", "--flag"] and entry["command"] == "prog --flag"
    assert entry["versions"]["jax"] == metadata.version("jax") and entry["cwd"] == os.getcwd()
    assert set(entry["git"]) == {"commit", "dirty"}
    import jax

    assert entry["platform"]["backend"] == jax.devices()[0].platform  # "cpu" here, "gpu" on the device
    assert entry["platform"]["platform_version"] == str(jax.devices()[0].client.platform_version)
    provenance.mark_startup("checked")  # a start-up step's end, in seconds since the process started
    later = provenance.provenance_entry(["prog"])["startup"]
    assert 0 < later["checked"] <= provenance.process_seconds() + 0.01 and "checked" not in entry["startup"]


def test_process_seconds_counts_from_the_process_start(tmp_path):
    import sys
    import time

    # a child that imports numpy first, then asks its age: at least its numpy import, at most its whole life
    script = ("import time; t = time.perf_counter(); import numpy; spent = time.perf_counter() - t; "
              "from lnnmpc.train.provenance import process_seconds; print(process_seconds(), spent)")
    begun = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, text=True).stdout
    lived = time.perf_counter() - begun
    age, numpy_import = (float(x) for x in out.split())
    assert numpy_import - 0.011 <= age <= lived + 0.011  # /proc's clock ticks: 10 ms
    assert provenance.process_seconds() > 0  # this test process, started before the test


def test_device_platform_reads_the_nvidia_driver_and_summary_names_it(tmp_path):
    line = ("NVRM version: NVIDIA UNIX x86_64 Kernel Module  580.159.04  Thu Oct  9 19:00:00 UTC 2025\n"
            "GCC version:  gcc version 12.3.0 (Ubuntu 12.3.0-1ubuntu1~22.04)\n")
    assert provenance.nvidia_driver_version(line) == "580.159.04"
    assert provenance.nvidia_driver_version("NVRM version: NVIDIA UNIX Open Kernel Module for x86_64  570.86.15  "
                                            "Release Build") == "570.86.15"
    assert provenance.nvidia_driver_version("") is None
    proc = tmp_path / "version"
    proc.write_text(line)
    assert provenance.device_platform(str(proc))["driver"] == "580.159.04"
    assert provenance.device_platform(str(tmp_path / "missing"))["driver"] is None  # no NVIDIA driver: a CPU
    assert provenance.driver_note([{"platform": {"driver": "1.2"}}, {"platform": {"driver": "580.159.04"}}]) \
        == " (driver 580.159.04)"  # the newest start's
    assert provenance.driver_note([{"git": {}}]) == "" and provenance.driver_note([]) == ""
