"""``experiments/scripts/compile_cache_check.sh`` on a fake GPU machine (an ``nvidia-smi`` and a PYTHON of a few shell
lines): the carried cache unpacked before the jobs start, every job launched side by side with the cache and its
share of the memory, and each job's compile.csv returned under $OUT."""

import os
import subprocess
import tarfile

SCRIPT = os.path.join(os.path.dirname(__file__), "..", "experiments", "scripts", "compile_cache_check.sh")

# a fake trainer: writes to its --out folder a compile.csv row with what it saw (its memory share, its cache flag,
# the cache entries present when it started)
FAKE_TRAINER = """out=""; cache=""
while [ $# -gt 0 ]; do
    case $1 in --out) out=$2;; --compile-cache) cache=$2;; esac; shift
done
mkdir -p "$out"
printf 'program,memory,cache,entries\\ntrain_chunk,%s,%s,%s\\n' "$XLA_PYTHON_CLIENT_MEM_FRACTION" "$cache" \\
    "$(find "$cache" -type f 2>/dev/null | wc -l)" > "$out/compile.csv"
echo trained"""


def _machine(tmp_path) -> dict:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "nvidia-smi").write_text("#!/bin/sh\necho 'Fake GPU, 1.0'\n")
    (bin_dir / "fake-python").write_text(f"#!/bin/sh\n{FAKE_TRAINER}\n")
    for tool in ("nvidia-smi", "fake-python"):
        os.chmod(bin_dir / tool, 0o755)
    return {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "PYTHON": str(bin_dir / "fake-python")}


def _run(tmp_path, glob: str, out) -> subprocess.CompletedProcess:
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("# two lines\nline-a --task cartpole-balance --seed 1\n\nline-b --task cartpole-balance --seed 2\n")
    out.mkdir()
    return subprocess.run(["bash", SCRIPT, glob, "30", str(jobs)], capture_output=True, text=True, timeout=60,
                          env={**_machine(tmp_path), "OUT": str(out)}, cwd=tmp_path / "repo")


def test_compile_cache_check_unpacks_the_split_archive_before_the_jobs(tmp_path):
    repo = tmp_path / "repo"
    cache = tmp_path / "made" / "runs" / "jaxcache"
    cache.mkdir(parents=True)
    for name in ("jit_a-cache", "jit_b-cache", "jit_c-cache"):
        (cache / name).write_bytes(os.urandom(3000))  # incompressible: the archive splits into several parts
    archive = tmp_path / "cache.tgz"
    with tarfile.open(archive, "w:gz") as tar:
        tar.add(cache, arcname="runs/jaxcache")
    data = archive.read_bytes()
    (tmp_path / "parts").mkdir()
    for index, start in enumerate(range(0, len(data), 4000)):
        (tmp_path / "parts" / f"cache.tgz.part-a{'abcdefgh'[index]}").write_bytes(data[start:start + 4000])
    assert len(os.listdir(tmp_path / "parts")) >= 3
    (repo / "runs" / "jaxcache").mkdir(parents=True)
    (repo / "runs" / "jaxcache" / "stale-entry").write_text("from an earlier check")  # replaced, not merged

    out = tmp_path / "out"
    result = _run(tmp_path, str(tmp_path / "parts" / "cache.tgz.part-*"), out)
    assert result.returncode == 0, result.stderr
    assert sorted(os.listdir(out)) == ["cache.txt", "line-a-compile.csv", "line-a.log", "line-b-compile.csv",
                                       "line-b.log"]
    for name in ("line-a", "line-b"):
        assert (out / f"{name}-compile.csv").read_text().splitlines()[1] == "train_chunk,0.45,runs/jaxcache,3"
        assert (out / f"{name}.log").read_text() == "trained\n"
    report = (out / "cache.txt").read_text().splitlines()
    assert report[0] == "Fake GPU, 1.0"
    assert report[1].startswith("cache entries before: 3, ")
    assert report[2].startswith("cache entries after: 3, ")
    assert sorted(os.listdir(repo / "runs" / "jaxcache")) == ["jit_a-cache", "jit_b-cache", "jit_c-cache"]


def test_compile_cache_check_without_an_archive_is_the_baseline(tmp_path):
    (tmp_path / "repo").mkdir()
    out = tmp_path / "out"
    result = _run(tmp_path, str(tmp_path / "no-such-part-*"), out)
    assert result.returncode == 0, result.stderr
    assert (out / "cache.txt").read_text().splitlines()[1] == "cache entries before: 0, 0 KiB"
    assert (out / "line-a-compile.csv").read_text().splitlines()[1] == "train_chunk,0.45,runs/jaxcache,0"
