"""``experiments/scripts/device_batch.sh`` on fake GPU machines (an ``nvidia-smi`` and a PYTHON of a few shell lines):
checking job lines, placing and relaunching jobs, limits, the report and the packing of results and policies."""

import os

import pytest

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


def test_device_batch_lint_passes_every_committed_jobs_file():
    """``device_batch.sh lint`` over every jobs file under experiments/scripts (the shape alone, no dry run): each
    committed file is one that ``start`` would launch, with no prose line that lost its '#' and no name twice."""
    import glob
    import subprocess

    files = sorted(glob.glob(os.path.join(os.path.dirname(DEVICE_BATCH), "jobs-*.txt")))
    assert len(files) > 100
    result = subprocess.run(["bash", DEVICE_BATCH, "lint", *files], capture_output=True, text=True, timeout=60)
    assert (result.returncode, result.stderr) == (0, ""), result.stderr[-2000:]
    assert result.stdout == f"ok      {len(files)} jobs file(s)\n"


def test_device_batch_lint_names_each_bad_line_and_start_launches_nothing_from_it(tmp_path):
    """A jobs file with a repeated job name, a note that lost its '#', a bad name and a bare name: ``lint`` names
    each line (FILE:LINE), ``check`` fails it, and ``start`` exits 2 before it launches anything."""
    import subprocess

    jobs = tmp_path / "jobs.txt"
    jobs.write_text("# header\nrun-a  --task cartpole-balance\nRan 2026-12-07 on one H100\n"
                    "run-a@0  --task cartpole-swingup\nbad/name  --task cartpole-balance\nbare\n"
                    "study-b  experiment fig5_19 --small\n")
    result = subprocess.run(["bash", DEVICE_BATCH, "lint", str(jobs)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.splitlines() == [
        f"{jobs}:3: Ran 2026-12-07 on one H100: a job line is <name> --<trainer arguments> or <name> experiment"
        " <study arguments> (a comment starts with #)",
        f"{jobs}:4: job name run-a again (line 2): each job of a file needs its own name",
        f"{jobs}:5: job name bad/name: give letters, digits, . _ or - (and @<gpu>)",
        f"{jobs}:6: bare: a job line is <name> --<trainer arguments> or <name> experiment <study arguments> (a"
        " comment starts with #)"]
    env = _fake_gpu_machine(tmp_path, 1, "echo launched; exit 0")
    check = subprocess.run(["bash", DEVICE_BATCH, "check", str(jobs)], capture_output=True, text=True, timeout=60,
                           env=env, cwd=tmp_path)
    assert check.returncode == 1 and f"{jobs}:4: job name run-a again" in check.stderr
    start = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "20"], capture_output=True, text=True,
                           timeout=60, env=env, cwd=tmp_path)
    assert start.returncode == 2 and f"{jobs}:3: Ran 2026-12-07" in start.stderr
    assert not (tmp_path / "runs" / "batch" / "commands.txt").exists()  # nothing launched
    missing = subprocess.run(["bash", DEVICE_BATCH, "lint", str(tmp_path / "none.txt")], capture_output=True,
                             text=True, timeout=60)
    assert missing.returncode == 1 and "none.txt: no such jobs file" in missing.stderr


def test_device_batch_start_launches_only_the_named_lines(tmp_path):
    """``ONLY=a,c device_batch.sh start``: only those lines of the file are launched (placed round robin among
    themselves); a name the file lacks stops it before any launch, naming the file's jobs."""
    import subprocess

    jobs = tmp_path / "jobs.txt"
    jobs.write_text("a  --task cartpole-balance\nb@1  --task cartpole-swingup\nc  --task acrobot-swingup\n")
    env = _fake_gpu_machine(tmp_path, 2, 'echo "gpu=$CUDA_VISIBLE_DEVICES $*"', MPS="0")
    wrong = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "20"], capture_output=True, text=True,
                           timeout=60, env={**env, "ONLY": "a,d"}, cwd=tmp_path)
    assert wrong.returncode == 2 and f"ONLY names no job of {jobs}: d; its jobs: a b c" in wrong.stderr
    assert not (tmp_path / "runs" / "batch" / "commands.txt").exists()
    result = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "20"], capture_output=True, text=True,
                            timeout=60, env={**env, "ONLY": "c,a"}, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    batch = tmp_path / "runs" / "batch"
    assert (batch / "commands.txt").read_text().splitlines() == [
        "a (GPU 0): --task cartpole-balance", "c (GPU 1): --task acrobot-swingup"]
    assert (batch / "c.log").read_text().startswith("gpu=1 -m lnnmpc.train.cli train --task acrobot-swingup")
    assert not (batch / "b.log").exists()


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


def test_device_batch_relaunch_does_not_wait_for_a_job_killed_from_outside(tmp_path):
    """A job whose launch was killed from outside (its wrapper process gone, so no NAME.rc was written) counts as
    ended: its NAME.rc becomes "gone", the report says so, and a relaunch neither waits RELAUNCH_WAIT seconds for
    it nor needs FORCE."""
    import signal
    import subprocess
    import time

    body = 'echo launched; [ -f first-done ] || { touch first-done; sleep 60; }'  # the first launch hangs
    env = _fake_gpu_machine(tmp_path, 1, body, RELAUNCH_WAIT="40", AFTER_POLL="0.05")
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("cut  --task cartpole-balance\n")
    batch = tmp_path / "runs" / "batch"
    start = lambda: subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "90", "0"], capture_output=True,
                                   text=True, timeout=60, env=env, cwd=tmp_path)
    assert start().returncode == 0
    deadline = time.monotonic() + 20
    while not ((batch / "cut.pid").exists() and (tmp_path / "first-done").exists()) and time.monotonic() < deadline:
        time.sleep(0.05)
    after = subprocess.run(["bash", DEVICE_BATCH, "after", "cut", "0", "sh", "-c", "echo ran"], capture_output=True,
                           text=True, timeout=60, env=env, cwd=tmp_path)
    assert after.returncode == 0, after.stderr
    os.killpg(int((batch / "cut.pid").read_text()), signal.SIGKILL)  # the wrapper and its job, as a `pkill` would
    deadline = time.monotonic() + 20  # `after` runs its command once the job has ended, killed or not
    while "ran" not in (batch / "after-cut.log").read_text() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (batch / "after-cut.log").read_text().startswith("cut ended (exit gone)")
    report = subprocess.run(["bash", DEVICE_BATCH, "wait", "0"], capture_output=True, text=True, timeout=60, env=env,
                            cwd=tmp_path)
    assert "ended: its process is gone without an exit status" in report.stdout, report.stdout
    assert "running: SIGTERM" not in report.stdout and (batch / "cut.rc").read_text().strip() == "gone"
    began = time.monotonic()
    relaunched = start()
    assert relaunched.returncode == 0, relaunched.stderr
    assert time.monotonic() - began < 20  # not RELAUNCH_WAIT's 40 s
    assert "still runs" not in relaunched.stderr and "ended: its process is gone" not in relaunched.stdout
    deadline = time.monotonic() + 20
    while not (batch / "cut.rc").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (batch / "cut.rc").read_text().strip() == "0"  # the relaunch's own exit status
    assert (batch / "cut.log").read_text() == "launched\nlaunched\n"
    lines = (batch / "commands.txt").read_text().splitlines()
    assert [line.split(":")[0] for line in lines] == ["cut (GPU 0)", "after cut (GPU 0)", "cut (GPU 0)"]
    assert (batch / "after-cut.log").read_text().endswith("ran\n")


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
    """The runs' policy.npz files travel in $OUT/policies.tar, not in results.tar.gz, in name order while they
    keep under POLICY_MIB, then the evaluations' policies; with one tar (POLICY_TARS=1) a file that would pass it is
    left out and named in the report, later ones still fit."""
    import subprocess
    import tarfile

    out = tmp_path / "out"
    out.mkdir()
    body = ('while [ $# -gt 0 ]; do case $1 in --out) run=$2;; --size) size=$2;; esac; shift; done; '
            'mkdir -p "$run/checkpoints"; echo rows >"$run/eval.csv"; head -c "$size" /dev/zero >"$run/policy.npz"; '
            'head -c 10 /dev/zero >"$run/checkpoints/policy.npz"; mkdir -p "$run/policies"; '
            'for step in 600 1200; do head -c 100 /dev/zero >"$run/policies/policy-$step.npz"; done')
    env = _fake_gpu_machine(tmp_path, 1, body, OUT=str(out), POLICY_MIB="1", POLICY_TARS="1")
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
    assert "policy left out (over POLICY_TARS=1 tars of POLICY_MIB=1): ./b/policy.npz" in report
    assert report.count("left out") == 1
    assert not (out / "policies-2.tar").exists()


def test_device_batch_fills_further_policies_tars_and_removes_an_empty_one(tmp_path):
    """With POLICY_TARS=3 each policy goes into the first tar it keeps under POLICY_MIB: policies.tar, then
    policies-2.tar ...; one that fits none is left out. A later pack that fills fewer tars removes those left empty
    from $OUT (the device tool would bring back a stale one)."""
    import subprocess
    import tarfile

    out = tmp_path / "out"
    out.mkdir()
    body = ('while [ $# -gt 0 ]; do case $1 in --out) run=$2;; --size) size=$2;; esac; shift; done; '
            'mkdir -p "$run"; echo rows >"$run/eval.csv"; head -c "$size" /dev/zero >"$run/policy.npz"')
    env = _fake_gpu_machine(tmp_path, 1, body, OUT=str(out), POLICY_MIB="1", POLICY_TARS="3")
    jobs = tmp_path / "jobs.txt"
    # 1 MiB each: a -> 1, b -> 2, c -> 1 (a + c fit), d -> 3 would fit alone, e fits nowhere left
    jobs.write_text("a --size 400000\nb --size 800000\nc --size 400000\nd --size 1000000\ne --size 300000\n")
    result = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "30"], capture_output=True,
                            text=True, timeout=60, env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    names = {}
    for tar_name in ("policies.tar", "policies-2.tar", "policies-3.tar"):
        with tarfile.open(out / tar_name) as tar:
            names[tar_name] = tar.getnames()
    assert names == {"policies.tar": ["./a/policy.npz", "./c/policy.npz"], "policies-2.tar": ["./b/policy.npz"],
                     "policies-3.tar": ["./d/policy.npz"]}
    report = (out / "report.txt").read_text()
    assert "policy left out (over POLICY_TARS=3 tars of POLICY_MIB=1): ./e/policy.npz" in report
    body_small = ('while [ $# -gt 0 ]; do case $1 in --out) run=$2;; esac; shift; done; '
                  'mkdir -p "$run"; echo rows >"$run/eval.csv"; head -c 1000 /dev/zero >"$run/policy.npz"')
    (tmp_path / "second").mkdir()
    env = _fake_gpu_machine(tmp_path / "second", 1, body_small, OUT=str(out), POLICY_MIB="1", POLICY_TARS="3")
    (tmp_path / "second" / "jobs.txt").write_text("f --steps 10\n")
    result = subprocess.run(["bash", DEVICE_BATCH, "start", str(tmp_path / "second" / "jobs.txt"), "60", "30"],
                            capture_output=True, text=True, timeout=60, env=env, cwd=tmp_path / "second")
    assert result.returncode == 0, result.stderr
    with tarfile.open(out / "policies.tar") as tar:  # another machine's batch folder: one small policy
        assert tar.getnames() == ["./f/policy.npz"]
    assert not (out / "policies-2.tar").exists() and not (out / "policies-3.tar").exists()


def test_device_batch_refuses_a_policies_tar_count_the_tool_cannot_return(tmp_path):
    """POLICY_TARS must leave room for report.txt and results.tar.gz among the 8 files the device tool returns."""
    import subprocess

    jobs = tmp_path / "jobs.txt"
    jobs.write_text("a --steps 10\n")
    for bad in ("0", "7", "two"):
        result = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "30"], capture_output=True,
                                text=True, timeout=60, env={**os.environ, "POLICY_TARS": bad}, cwd=tmp_path)
        assert result.returncode == 2
        assert f"POLICY_TARS={bad} must be 1 to 6" in result.stderr


_ONE_POLICY = 'head -c 600000 /dev/zero >"$run/policy.npz"'
_WITH_EVALUATIONS = ('head -c 300000 /dev/zero >"$run/policy.npz"; mkdir -p "$run/policies"; '
                     'for step in 600 1200; do head -c 300000 /dev/zero >"$run/policies/policy-$step.npz"; done')


@pytest.mark.parametrize("writes, files", [
    (_ONE_POLICY, ["policy.npz"]),
    (_WITH_EVALUATIONS, ["policy.npz", "policies/policy-1200.npz", "policies/policy-600.npz"])])
def test_device_batch_packs_the_latest_starts_policies_first(tmp_path, writes, files):
    """A second start on the same machine packs the policies its runs wrote (their policy.npz, then with
    --eval-policies their evaluations' policies) before any of the earlier start's runs' files, which the earlier
    call's policies.tar brought back already: here one run's files fill the one tar, and they are the new run's; the
    earlier run's are named left out."""
    import subprocess
    import tarfile

    out = tmp_path / "out"
    out.mkdir()
    body = ('while [ $# -gt 0 ]; do case $1 in --out) run=$2;; esac; shift; done; '
            f'mkdir -p "$run"; echo rows >"$run/eval.csv"; {writes}')
    env = _fake_gpu_machine(tmp_path, 1, body, OUT=str(out), POLICY_MIB="1", POLICY_TARS="1")
    for name in ("a-earlier", "z-later"):  # the earlier start's run comes first by name
        jobs = tmp_path / f"{name}.txt"
        jobs.write_text(f"{name} --steps 10\n")
        result = subprocess.run(["bash", DEVICE_BATCH, "start", str(jobs), "60", "30"], capture_output=True,
                                text=True, timeout=60, env=env, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        with tarfile.open(out / "policies.tar") as tar:
            assert tar.getnames() == [f"./{name}/{file}" for file in files]
    report = (out / "report.txt").read_text()
    for file in files:
        assert f"policy left out (over POLICY_TARS=1 tars of POLICY_MIB=1): ./a-earlier/{file}" in report
    assert report.count("left out") == len(files)


def test_device_batch_sends_a_policy_over_the_limit_in_parts_that_ingest_batch_joins(tmp_path):
    """A policy.npz over POLICY_MIB (TD-MPC2's 5M model) goes in equal parts, one per tar where each fits no other
    way; ``ingest_batch.sh`` joins them byte for byte. With one tar too few the report names the part left out and
    ingest files no policy for that run rather than a truncated one."""
    import subprocess
    import tarfile

    ingest = os.path.join(os.path.dirname(DEVICE_BATCH), "ingest_batch.sh")
    body = ('while [ $# -gt 0 ]; do case $1 in --out) run=$2;; esac; shift; done; '
            'mkdir -p "$run"; echo rows >"$run/eval.csv"; echo "{}" >"$run/config.json"; '
            'head -c 2621440 /dev/urandom >"$run/policy.npz"')  # 2.5 MiB: three parts of 1 MiB tars
    for tars, complete in (("3", True), ("2", False)):
        root = tmp_path / f"tars{tars}"
        out = root / "out"
        out.mkdir(parents=True)
        env = _fake_gpu_machine(root, 1, body, OUT=str(out), POLICY_MIB="1", POLICY_TARS=tars)
        (root / "jobs.txt").write_text("big --steps 10\n")
        result = subprocess.run(["bash", DEVICE_BATCH, "start", str(root / "jobs.txt"), "60", "30"],
                                capture_output=True, text=True, timeout=60, env=env, cwd=root)
        assert result.returncode == 0, result.stderr
        names = []
        for tar_name in ("policies.tar", "policies-2.tar", "policies-3.tar"):
            if (out / tar_name).exists():
                with tarfile.open(out / tar_name) as tar:
                    names.append(tar.getnames())
                    assert all(m.size <= 1048576 for m in tar.getmembers())
        expected = [[f"./big/policy.npz.part-{k}-of-3"] for k in (1, 2, 3)]
        assert names == (expected if complete else expected[:2])
        with tarfile.open(out / "results.tar.gz") as tar:
            assert not [n for n in tar.getnames() if "policy" in n or ".parts" in n]
        report = (out / "report.txt").read_text()
        assert ("left out" in report) is not complete
        if not complete:
            assert "policy left out (over POLICY_TARS=2 tars of POLICY_MIB=1): ./big/policy.npz.part-3-of-3" in report
        work = root / "work"
        work.mkdir()
        result = subprocess.run(["bash", ingest, str(out / "results.tar.gz")], cwd=work, timeout=120,
                                env={**os.environ, "PYTHON": "true"}, capture_output=True, text=True)
        assert result.returncode == 0, result.stderr
        staged = work / "runs" / "ingested" / "big"
        assert not list(staged.glob("*.part-*"))
        if complete:
            assert "joined   big/policy.npz from its 3 parts" in result.stdout
            assert (staged / "policy.npz").read_bytes() == (root / "runs" / "batch" / "big" / "policy.npz").read_bytes()
        else:
            assert "missing  big/policy.npz: 2 of its 3 parts came back" in result.stdout
            assert not (staged / "policy.npz").exists()
