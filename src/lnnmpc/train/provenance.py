"""Where a run came from: the command, the code and the software, recorded in its config.json.

Every start and every resume of a run appends one entry to ``config.json``'s ``"provenance"`` list, so a run that
was stopped and resumed on another machine says so:

    {"time": "2026-11-27T13:23:40Z", "command": "python -m lnnmpc.train.cli train --task walker-run ...",
     "argv": [...], "cwd": "/work/main", "host": "gpu-7", "python": "3.12.3",
     "git": {"commit": "827c1e3...", "dirty": false}, "versions": {"jax": "0.11.2", ...},
     "platform": {"backend": "gpu", "platform_version": "...", "driver": "580.159.04", "xla_flags": ""},
     "startup": {"imports": 4.1, "devices": 9.8, "built": 12.0, "validated": 14.2}}

``startup`` gives the seconds since the process started at which each start-up step ended (:func:`mark_startup`;
empty where ``/proc`` cannot tell): where the ``startup`` row of ``timing.csv`` goes.

``git`` is ``{"commit": None, "dirty": None}`` where the code is not in a git checkout (an installed wheel, a
copied snapshot) or git is missing, and where the code lies in a checkout's git-ignored folder (a snapshot
unpacked under ``runs/``): that checkout's HEAD says nothing of it. A snapshot made by
``experiments/scripts/snapshot.sh`` carries its commit in a ``SNAPSHOT_COMMIT`` file beside its ``src/``; the code then
reports ``{"commit": <that hash>, "dirty": False, "snapshot": <the snapshot's folder>}``.
"""

from __future__ import annotations

import os
import platform
import re
import shlex
import subprocess
import sys
import time
from importlib import metadata

PACKAGES = ("jax", "jaxlib", "flax", "optax", "chex", "orbax-checkpoint", "mujoco", "mujoco-mjx", "dm-control")
_PACKAGE_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # .../lnnmpc


def software_versions(packages: tuple[str, ...] = PACKAGES) -> dict[str, str | None]:
    """Installed version of each package (None where it is not installed)."""
    versions = {}
    for package in packages:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    return versions


SNAPSHOT_FILE = "SNAPSHOT_COMMIT"  # in a code snapshot's folder, beside its src/: the commit it was archived from


def snapshot_commit(path: str = _PACKAGE_ROOT) -> tuple[str, str] | None:
    """(commit, snapshot folder) when the package at ``path`` (``<snapshot>/src/lnnmpc``) is a snapshot with a
    ``SNAPSHOT_COMMIT`` file, else None."""
    folder = os.path.dirname(os.path.dirname(os.path.abspath(path)))
    try:
        with open(os.path.join(folder, SNAPSHOT_FILE)) as f:
            commit = f.read().strip()
    except OSError:
        return None
    return (commit, folder) if commit else None


def git_state(path: str = _PACKAGE_ROOT) -> dict[str, str | bool | None]:
    """``{"commit": HEAD's hash, "dirty": whether tracked files differ from it}`` of the checkout holding
    ``path``; a snapshot's own commit (module docstring); both None outside a git checkout, in a folder that
    checkout ignores, or without git."""
    snapshot = snapshot_commit(path)
    if snapshot:
        return {"commit": snapshot[0], "dirty": False, "snapshot": snapshot[1]}

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", path, *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if not commit or git("check-ignore", "-q", os.path.abspath(path)) is not None:
        return {"commit": None, "dirty": None}
    status = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def process_seconds() -> float | None:
    """Seconds since this process started (Linux ``/proc``: the interpreter's start, imports and device
    initialisation included; 10 ms resolution), None where ``/proc`` cannot tell."""
    try:
        with open("/proc/self/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()  # after the command name: field 3 (state) onwards
        with open("/proc/uptime") as uptime:
            since_boot = float(uptime.read().split()[0])
        return max(0.0, since_boot - int(fields[19]) / os.sysconf("SC_CLK_TCK"))  # field 22: start, clock ticks
    except (OSError, ValueError, IndexError):
        return None


_STARTUP_MARKS: dict[str, float] = {}


def mark_startup(name: str) -> None:
    """Notes :func:`process_seconds` now as the end of start-up step ``name`` (the trainer marks imports,
    devices, environments and agent built, validated); the next :func:`provenance_entry` records them."""
    seconds = process_seconds()
    if seconds is not None:
        _STARTUP_MARKS[name] = round(seconds, 2)


def command_line(argv: list[str]) -> str:
    """``argv`` as a shell command; a script inside the lnnmpc package becomes ``python -m lnnmpc.<module>``."""
    if not argv:
        return ""
    script = os.path.abspath(argv[0])
    if script.startswith(_PACKAGE_ROOT + os.sep) and script.endswith(".py"):
        relative = os.path.relpath(script[:-3], os.path.dirname(_PACKAGE_ROOT))
        head = ["python", "-m", relative.replace(os.sep, ".").removesuffix(".__main__")]
    else:
        head = [argv[0]]
    return shlex.join(head + list(argv[1:]))


def nvidia_driver_version(text: str) -> str | None:
    """The driver version in the text of ``/proc/driver/nvidia/version`` (``NVRM version: NVIDIA UNIX x86_64
    Kernel Module  580.159.04  ...`` gives ``"580.159.04"``), None where it names none."""
    match = re.search(r"Kernel Module\s+(?:for \S+\s+)?(\d+(?:\.\d+)+)", text)
    return match.group(1) if match else None


def device_platform(proc_version: str = "/proc/driver/nvidia/version") -> dict[str, str | None]:
    """The platform this process computes on: the backend of its first device and the backend's
    ``platform_version`` string, both of which JAX's persistent compile cache hashes into its keys (a cache written
    under another one misses), the NVIDIA kernel driver (None without one) and the ``XLA_FLAGS`` it started
    under (``--deterministic`` adds one): ``{"backend": "gpu", "platform_version": "...", "driver": "580.159.04",
    "xla_flags": ""}``."""
    import jax

    device = jax.devices()[0]
    try:
        with open(proc_version) as f:
            driver = nvidia_driver_version(f.read())
    except OSError:
        driver = None
    return {"backend": device.platform, "platform_version": str(device.client.platform_version), "driver": driver,
            "xla_flags": os.environ.get("XLA_FLAGS", "")}


def provenance_entry(argv: list[str] | None = None) -> dict:
    """One entry of the ``"provenance"`` list for a start (or resume) now, by ``argv`` (default ``sys.argv``)."""
    argv = list(sys.argv if argv is None else argv)
    return {"time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": command_line(argv),
            "argv": argv, "cwd": os.getcwd(), "host": platform.node(), "python": platform.python_version(),
            "git": git_state(), "versions": software_versions(), "platform": device_platform(),
            "startup": dict(_STARTUP_MARKS)}


def driver_note(entries: list[dict]) -> str:
    """`` (driver 580.159.04)`` for summary.md's devices row where the newest start recorded an NVIDIA driver,
    else empty."""
    driver = ((entries[-1].get("platform") or {}).get("driver")) if entries else None
    return f" (driver {driver})" if driver else ""


def code_line(entries: list[dict]) -> str:
    """The code and versions of the newest entry (start or resume) for summary.md, and how many starts there
    were: ``827c1e3d0a12 (uncommitted changes); jax 0.11.2, mujoco-mjx 3.17.0; 2 starts (resumed)``."""
    if not entries:
        return "not recorded"
    latest = entries[-1]
    git = latest.get("git") or {}
    code = (git["commit"][:12] + (" (uncommitted changes)" if git.get("dirty") else "")
            + (" (snapshot)" if git.get("snapshot") else "") if git.get("commit") else "not a git checkout")
    versions = latest.get("versions") or {}
    shown = ", ".join(f"{name} {versions[name]}" for name in ("jax", "mujoco-mjx") if versions.get(name))
    starts = f"; {len(entries)} starts (resumed)" if len(entries) > 1 else ""
    return code + (f"; {shown}" if shown else "") + starts


# Since this commit (2026-11-29) the trainer's and `cli eval`'s MJX episodes take their keys as they are derived now
# (episode i's from fold_in(key, i); :func:`lnnmpc.train.loop.evaluation_keys`): runs started before it played other
# starts. A run's provenance names its code's commit (the time where git does not know the commit: a shallow clone).
KEYS_SINCE_COMMIT, KEYS_SINCE_TIME = "45dda0c", "2026-11-29T17:23:29Z"


def plays_current_starts(entry: dict) -> bool:
    """Whether a provenance entry ran code whose evaluations draw their starts as today's code does: its commit
    descends from KEYS_SINCE_COMMIT (or, where git cannot tell, it started after KEYS_SINCE_TIME)."""
    commit = (entry.get("git") or {}).get("commit")
    if commit:
        root = os.path.join(_PACKAGE_ROOT, "..", "..")
        done = subprocess.run(["git", "-C", root, "merge-base", "--is-ancestor", KEYS_SINCE_COMMIT, commit],
                              capture_output=True)
        if done.returncode in (0, 1):  # 128: a commit git does not know
            return done.returncode == 0
    return str(entry.get("time", "")) >= KEYS_SINCE_TIME


def check_current_starts(run: str) -> None:
    """ConfigError where ``run`` has no provenance or a start or resume of it ran code older than KEYS_SINCE_COMMIT
    (its evaluations' starts cannot be recomputed, nor matched with another run's)."""
    from lnnmpc.train import runfolder
    from lnnmpc.train.config import ConfigError

    entries = runfolder.read_provenance(run)
    old = [e for e in entries if not plays_current_starts(e)]
    if not entries or old:
        when = f"started at {old[0].get('time', '?')}" if old else "records no provenance"
        raise ConfigError(f"{run!r} {when}: its evaluations drew their starts before {KEYS_SINCE_COMMIT} "
                          f"({KEYS_SINCE_TIME[:10]}), so they cannot be recomputed")
