"""``experiments/scripts/final_evals.sh`` with a fake PYTHON (a few shell lines standing in for ``cli eval``): which
evaluations it launches for which runs, with what memory share, how it reports a failed one, what it packs."""

import os
import subprocess
import tarfile

FINAL_EVALS = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "final_evals.sh")

# Stands in for `python -m lnnmpc.train.cli eval RUN [--backend B] --episodes N --out CSV`: writes CSV with one row
# per episode and prints cli eval's summary line; a run whose name holds "broken" fails on dm_control.
FAKE_PYTHON = r"""#!/usr/bin/env bash
run=$4; backend=mjx; out=; episodes=
shift 4
while [ $# -gt 0 ]; do
    case $1 in --backend) backend=$2; shift 2 ;; --out) out=$2; shift 2 ;; --episodes) episodes=$2; shift 2 ;;
    *) echo "unexpected $1"; exit 9 ;; esac
done
echo "memory $XLA_PYTHON_CLIENT_MEM_FRACTION"
if [ "$backend" = dm_control ] && [[ $run == *broken* ]]; then echo "Error: dm_control failed on $run"; exit 3; fi
echo "episode,return" > "$out"
for ((i = 0; i < episodes; i++)); do echo "$i,1$i.5" >> "$out"; done
printf '[###] 1/1\r'
echo "acrobot-swingup cfc-zp-det checkpoint 200,256 on $backend with clean: return 1$episodes.5 ± 1.0 -> $out"
"""


def _setup(tmp_path, names):
    fake = tmp_path / "fake-python"
    fake.write_text(FAKE_PYTHON)
    fake.chmod(0o755)
    for name in names:
        (tmp_path / "runs" / "batch" / name).mkdir(parents=True)
        (tmp_path / "runs" / "batch" / name / "policy.npz").write_bytes(b"")
    out = tmp_path / "out"
    out.mkdir()
    return {**os.environ, "PYTHON": str(fake), "OUT": str(out)}, out


def _run(tmp_path, env, *args, **extra):
    return subprocess.run(["bash", FINAL_EVALS, *args], capture_output=True, text=True, timeout=60, cwd=tmp_path,
                          env={**env, **extra})


def test_final_evals_runs_both_measures_per_run_and_packs_them_in_one_tarball(tmp_path):
    env, out = _setup(tmp_path, ["line-seed1", "line-seed2"])
    done = _run(tmp_path, env, "line-seed1", "line-seed2", DMC_EPISODES="3")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        *(f"acrobot-swingup cfc-zp-det checkpoint 200,256 on {backend} with clean: return 1{n}.5 ± 1.0 -> "
          f"runs/batch/{prefix}-line-seed{seed}.csv"
          for seed in (1, 2) for backend, n, prefix in (("mjx", 20, "mjx-20ep"), ("dm_control", 3, "dm_control"))),
        f"packed 8 file(s) into {out}/final-evals.tar.gz"]
    with tarfile.open(out / "final-evals.tar.gz") as tar:
        names = sorted(tar.getnames())
        assert names == sorted(f"runs/batch/{kind}-line-seed{seed}.{ext}" for seed in (1, 2)
                               for kind, ext in (("mjx-20ep", "csv"), ("eval", "log"), ("dm_control", "csv"),
                                                 ("dm_control", "log")))
        rows = tar.extractfile("runs/batch/dm_control-line-seed2.csv").read().decode().splitlines()
        assert rows == ["episode,return", "0,10.5", "1,11.5", "2,12.5"]
        log = tar.extractfile("runs/batch/eval-line-seed1.log").read().decode()
        assert log.startswith("memory 0.23\n")  # 0.9 shared by four processes, to two decimals
    assert sorted(os.listdir(out)) == ["final-evals.tar.gz"]


def test_final_evals_names_a_failed_evaluation_and_still_packs_the_others(tmp_path):
    env, out = _setup(tmp_path, ["broken-seed1"])
    done = _run(tmp_path, env, "broken-seed1", MEM_FRACTION="0.3", MJX_EPISODES="2")
    assert done.returncode == 1
    assert done.stderr == "FAILED  runs/batch/dm_control-broken-seed1.log: Error: dm_control failed on " \
                          "runs/batch/broken-seed1\n"
    with tarfile.open(out / "final-evals.tar.gz") as tar:
        assert sorted(tar.getnames()) == ["runs/batch/dm_control-broken-seed1.log", "runs/batch/eval-broken-seed1.log",
                                          "runs/batch/mjx-2ep-broken-seed1.csv"]
        assert tar.extractfile("runs/batch/eval-broken-seed1.log").read().decode().startswith("memory 0.3\n")


def test_final_evals_refuses_bad_input_before_it_launches_anything(tmp_path):
    env, out = _setup(tmp_path, ["ran-seed1"])
    usage = _run(tmp_path, env)
    assert (usage.returncode, usage.stderr) == (2, "usage: final_evals.sh NAME... (run folders under runs/batch)\n")
    missing = _run(tmp_path, env, "ran-seed1", "gone-seed2", "gone-seed3")
    assert missing.returncode == 1
    assert missing.stderr.splitlines() == [
        f"runs/batch/gone-seed{seed}/policy.npz: no such file (a finished run of device_batch.sh has one)"
        for seed in (2, 3)]
    for var, value in (("DMC_EPISODES", "0"), ("MJX_EPISODES", "ten"), ("TIMEOUT", "-5")):
        bad = _run(tmp_path, env, "ran-seed1", **{var: value})
        assert (bad.returncode, bad.stderr) == (2, f"{var}={value} must be a positive whole number\n")
    no_out = _run(tmp_path, {k: v for k, v in env.items() if k != "OUT"}, "ran-seed1")
    assert (no_out.returncode, no_out.stderr) == (
        2, "set OUT, the folder whose files come back (the device tool sets it)\n")
    assert os.listdir(out) == [] and sorted(os.listdir(tmp_path / "runs" / "batch")) == ["ran-seed1"]


def test_final_evals_dry_run_prints_the_commands(tmp_path):
    env, out = _setup(tmp_path, ["ran-seed1"])
    dry = _run(tmp_path, env, "ran-seed1", DRY="1")
    python = env["PYTHON"]
    assert (dry.returncode, dry.stderr) == (0, "")
    assert dry.stdout.splitlines() == [
        f"{python} -m lnnmpc.train.cli eval runs/batch/ran-seed1 --episodes 20 --out runs/batch/mjx-20ep-ran-seed1.csv"
        " > runs/batch/eval-ran-seed1.log",
        f"{python} -m lnnmpc.train.cli eval runs/batch/ran-seed1 --backend dm_control --episodes 10 --out "
        "runs/batch/dm_control-ran-seed1.csv > runs/batch/dm_control-ran-seed1.log"]
    assert os.listdir(out) == []
