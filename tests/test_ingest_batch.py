"""``experiments/scripts/ingest_batch.sh`` (a device batch's results filed into the repository) and
``throughput_ab.sh`` (two snapshots' throughput benchmark with the same arguments), on fake batches."""

import csv
import os

from run_folders import fake_run, write_rows


def test_ingest_batch_files_study_runs_ranks_and_whole_tables(tmp_path):
    """``ingest_batch.sh``: a device batch's results.tar.gz becomes study-runs/ folders, their effective-rank
    figures and every agent's row of the study's table (the job line's --agents dropped)."""
    import json
    import subprocess
    import sys
    import tarfile

    batch = tmp_path / "batch"
    run_dir = batch / "experiments" / "acrobot-swingup" / "tdmpc2" / "noise0.1-seeds1"
    fake_run(str(run_dir), 50_000, checkpoint=False, returns=[[10.0, 30.0]], eval_name="mjx-noise0.1-50000.csv")
    (run_dir / "config.json").write_text(json.dumps({"config": {"task": "acrobot-swingup", "agent": "tdmpc2"},
                                                     "agent_config": {"model": {"latent_dim": 8}}}))
    write_rows(str(run_dir / "eval.csv"), [{"env_step": 50_000, "seed": 0, "episode": e, "return": 1.0,
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
            fake_run(str(batch / "experiments" / rel), last, checkpoint=False)
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


def test_ingest_batch_unpacks_every_policies_tar(tmp_path):
    """Where device_batch.sh filled policies.tar and went on into policies-2.tar, both are unpacked beside the run:
    the staged run holds the policies of each, and the output counts each tar's files."""
    import subprocess
    import tarfile

    batch = tmp_path / "batch"
    run = batch / "acro"
    (run / "policies").mkdir(parents=True)
    (run / "config.json").write_text("{}")
    with tarfile.open(tmp_path / "results.tar.gz", "w:gz") as tar:
        tar.add(batch, arcname=".")
    parts = {"policies.tar": {"policy.npz": b"final", "policies/policy-1200.npz": b"at 1200"},
             "policies-2.tar": {"policies/policy-600.npz": b"at 600"}}
    for name, files in parts.items():
        with tarfile.open(tmp_path / name, "w") as tar:
            for rel, data in files.items():
                (run / rel).write_bytes(data)
                tar.add(run / rel, arcname=f"./acro/{rel}")
                (run / rel).unlink()
    script = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "ingest_batch.sh")
    work = tmp_path / "work"
    work.mkdir()
    result = subprocess.run(["bash", script, str(tmp_path / "results.tar.gz")], cwd=work, timeout=120,
                            env={**os.environ, "PYTHON": "true"}, capture_output=True, text=True)  # no tables
    assert result.returncode == 0, result.stderr
    staged = work / "runs" / "ingested" / "acro"
    assert (staged / "policy.npz").read_bytes() == b"final"
    assert (staged / "policies" / "policy-1200.npz").read_bytes() == b"at 1200"
    assert (staged / "policies" / "policy-600.npz").read_bytes() == b"at 600"
    assert f"policies 1 policy.npz from {tmp_path / 'policies.tar'}" in result.stdout
    assert f"policies 0 policy.npz from {tmp_path / 'policies-2.tar'}" in result.stdout
    assert result.stdout.count("1 evaluations' policies") == 2


def test_ingest_batch_files_no_part_of_a_policy_whose_first_part_stayed_behind(tmp_path):
    """A policy that came in parts with its first part missing is named and none of its parts is filed: no stray
    ``policy.npz.part-*`` in the staged run, no truncated ``policy.npz``."""
    import subprocess
    import tarfile

    batch = tmp_path / "batch"
    run = batch / "tdmpc2-run"
    run.mkdir(parents=True)
    (run / "config.json").write_text("{}")
    with tarfile.open(tmp_path / "results.tar.gz", "w:gz") as tar:
        tar.add(batch, arcname=".")
    (run / "policy.npz.part-2-of-2").write_bytes(b"second half")
    with tarfile.open(tmp_path / "policies-2.tar", "w") as tar:
        tar.add(run / "policy.npz.part-2-of-2", arcname="./tdmpc2-run/policy.npz.part-2-of-2")
    script = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "ingest_batch.sh")
    work = tmp_path / "work"
    work.mkdir()
    result = subprocess.run(["bash", script, str(tmp_path / "results.tar.gz")], cwd=work, timeout=120,
                            env={**os.environ, "PYTHON": "true"}, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "missing  tdmpc2-run/policy.npz: 1 of its 2 parts came back" in result.stdout
    staged = work / "runs" / "ingested" / "tdmpc2-run"
    assert sorted(p.name for p in staged.iterdir()) == ["config.json"]
