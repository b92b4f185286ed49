"""Run folders: naming, the saved configuration and the CSV logs.

A run folder holds ``config.json`` (the resolved :class:`TrainConfig` plus derived settings), ``train.csv``,
``eval.csv``, ``checkpoints/``, ``curve.png``, ``summary.md`` and ``.lock`` (:func:`hold_run`). CSV files are
appended to after every chunk and truncated back to a checkpoint's environment step when a run resumes, so that
they always describe exactly the training that the newest checkpoint continues.
"""

from __future__ import annotations

import csv
import fcntl
import io
import json
import os
import tempfile
import time
from collections.abc import Callable
from typing import IO

from lnnmpc.train.config import ConfigError, TrainConfig, obs_tag

CONFIG_FILE = "config.json"
LOCK_FILE = ".lock"  # held (flock) by the process training in the folder; holds its pid


def new_run_path(config: TrainConfig) -> str:
    """``out``, or ``<runs_dir>/<task>/<agent>/<timestamp>-<name>`` (name: the corruption tag by default)."""
    if config.out:
        return config.out
    name = config.name or obs_tag(config.obs)
    return os.path.join(config.runs_dir, config.task, config.agent, f"{time.strftime('%Y%m%d-%H%M%S')}-{name}")


def ensure_writable(folder: str) -> None:
    """Creates ``folder`` and checks that a file can be written there (ConfigError naming it otherwise)."""
    try:
        os.makedirs(folder, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-test-"):
            pass
    except OSError as error:
        raise ConfigError(f"output folder {folder!r} is not writable: {error.strerror or error}") from None


def hold_run(folder: str) -> IO:
    """An exclusive lock on the run folder ``folder`` (existing) for as long as the returned file stays open (a
    context manager; the process's exit releases it too): a second training process on the same folder, e.g. a
    resume started while the first still finishes its chunk and checkpoint after SIGTERM, raises ConfigError
    naming the folder and the holder's pid instead of writing the same checkpoints and CSV files at once."""
    handle = open(os.path.join(folder, LOCK_FILE), "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        holder = handle.read().strip() or "unknown"
        handle.close()
        raise ConfigError(f"run folder {folder!r} is in use by another training process (pid {holder}): wait for "
                          "it to end (on SIGTERM or Ctrl-C it saves a checkpoint after its running chunk) or give "
                          "another output folder") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle


def check_creatable(folder: str) -> None:
    """Like :func:`ensure_writable` without creating anything: ``folder`` or its nearest existing parent must be a
    writable folder (ConfigError naming it otherwise)."""
    existing = os.path.abspath(folder)
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing) or not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"output folder {folder!r} cannot be created: {existing!r} is not a writable folder")


def write_config(run: str, config: TrainConfig, derived: dict) -> None:
    """Writes config.json atomically: ``{"config": TrainConfig fields, **derived}``."""
    write_text(os.path.join(run, CONFIG_FILE),
               json.dumps({"config": config.to_dict(), **derived}, indent=2, default=str))


def read_config(run: str) -> dict:
    """The JSON of a run folder's config.json (ConfigError if the folder is no run folder)."""
    path = os.path.join(run, CONFIG_FILE)
    if not os.path.isfile(path):
        raise ConfigError(f"{run!r} is not a run folder (no {CONFIG_FILE})")
    with open(path) as f:
        data = json.load(f)
    if "config" not in data:
        raise ConfigError(f"{path} was written by an older trainer (no 'config' entry); start a new run")
    return data


def read_provenance(run: str) -> list[dict]:
    """The ``"provenance"`` entries (:mod:`lnnmpc.train.provenance`) of a run folder's config.json; [] where the
    folder has no config.json yet or it predates them."""
    if not os.path.isfile(os.path.join(run, CONFIG_FILE)):
        return []
    return list(read_config(run).get("provenance", []))


def saved_config(run: str, **changes) -> TrainConfig:
    """The TrainConfig stored in a run folder, with ``changes`` applied; ``out`` points at the folder."""
    values = dict(read_config(run)["config"])
    values.pop("compile_cache", None)  # machine-specific: use this machine's default unless changed
    return TrainConfig.from_dict(values, out=run, **changes)


def append_csv(path: str, rows: list[dict]) -> None:
    """Appends rows to a CSV file, writing the header for a new file.

    Rows may bring columns the file lacks (the seed phase's train.csv rows have no losses): then the file is
    rewritten atomically with the union of the columns, earlier rows leaving the new ones empty.
    """
    if not rows:
        return
    fields = list(dict.fromkeys(key for row in rows for key in row))
    if os.path.exists(path):
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            header, old = list(reader.fieldnames or []), list(reader)
        if set(fields) <= set(header):
            with open(path, "a", newline="") as f:
                csv.DictWriter(f, fieldnames=header).writerows(rows)
            return
        rows, fields = old + rows, header + [k for k in fields if k not in header]
    write_csv(path, fields, rows)


def write_atomic(path: str, write: Callable[[IO], None], binary: bool = False) -> None:
    """Writes a whole file atomically: ``write(f)`` fills a temporary file of this process (several processes
    may write the same file at once, e.g. two studies rebuilding one table), which is renamed over ``path``."""
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "wb") if binary else open(tmp, "w", newline="") as f:
        write(f)
    os.replace(tmp, path)


def write_text(path: str, text: str) -> None:
    """Writes ``text`` to ``path`` atomically (:func:`write_atomic`)."""
    write_atomic(path, lambda f: f.write(text))


def write_csv(path: str, fields: list[str], rows: list[dict]) -> None:
    """Writes a whole CSV file atomically (:func:`write_text`)."""
    buffer = io.StringIO(newline="")
    writer = csv.DictWriter(buffer, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, buffer.getvalue())


def read_csv(path: str) -> list[dict]:
    if not os.path.exists(path):
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def truncate_csv(path: str, max_env_step: int) -> None:
    """Drops rows with env_step > max_env_step (written after a checkpoint), atomically; -1 drops all."""
    if not os.path.exists(path):
        return
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        fields, rows = reader.fieldnames, [r for r in reader if int(r["env_step"]) <= max_env_step]
    if not rows:
        os.remove(path)
        return
    write_csv(path, fields, rows)
