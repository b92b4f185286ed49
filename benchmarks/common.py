"""Helpers shared by the benchmarks: environment metadata, timing with medians, JSON output."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import re
import statistics
import time

import jax
import numpy as np

from lnnmpc.train.checkpoint import keys_as_data
from lnnmpc.train.provenance import git_state, software_versions


def environment_info() -> dict:
    """Device, package versions and the code's commit (``git_state``: a snapshot's own commit on a device
    batch), recorded in every benchmark JSON."""
    device = jax.devices()[0]
    versions = software_versions(("jax", "jaxlib", "flax", "optax", "mujoco", "mujoco-mjx", "dm-control"))
    return {
        "device": device.device_kind,
        "platform": device.platform,
        "device_count": jax.device_count(),
        "python": platform.python_version(),
        "versions": versions,
        "git": git_state(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def time_call(fn, *args, repeats: int = 5, keep_output: bool = False) -> dict:
    """Compiles/warms ``fn`` once, then times ``repeats`` calls; seconds, median first. With ``keep_output`` the
    last call's result is returned too (``output``), for a caller that also needs what the call computed."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        out = None  # the previous result freed before the next call
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    timing = {"median_s": statistics.median(times), "min_s": min(times), "times_s": times, "first_call_s": first}
    return {**timing, "output": out} if keep_output else timing


def tree_digest(tree) -> str:
    """SHA-256 (hex) of every leaf's dtype, shape and bytes, in ``jax.tree`` order (typed PRNG keys by their key
    data, as ``checkpoint.keys_as_data`` gives them): equal digests mean bit-identical pytrees (e.g. a program's
    output in two processes; on a GPU only under deterministic ops, see ``train_throughput.time_chunk``)."""
    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(keys_as_data(tree)):
        array = np.ascontiguousarray(np.asarray(leaf))
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def compiled_gflop(compiled) -> float | None:
    """GFLOP of one call of a compiled program (``jax.jit(f).lower(...).compile()``) by XLA's cost analysis (None
    where the backend gives none). Set against the call's time it says how far from compute-bound the call is."""
    cost = compiled.cost_analysis()
    if isinstance(cost, (list, tuple)):  # older jax: one dict per device
        cost = cost[0] if cost else None
    flops = (cost or {}).get("flops")
    return None if flops is None or flops < 0 else flops / 1e9


def peak_memory_bytes() -> int | None:
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def device_tag(kind: str, platform: str) -> str:
    """A short name for a device in file names: ``cpu``, the model number of a GPU (``NVIDIA H100 80GB HBM3`` ->
    ``h100``, ``NVIDIA H200`` -> ``h200``), else the device kind as a lower-case slug."""
    if platform == "cpu":
        return "cpu"
    model = re.search(r"\b([a-z]{1,2}\d{2,4}[a-z]?)\b", kind.lower())
    return model.group(1) if model else re.sub(r"[^a-z0-9]+", "-", kind.lower()).strip("-") or platform


def expand_device(path: str) -> str:
    """``path`` with ``{device}`` replaced by the device this process runs on (:func:`device_tag`), so that a
    command written before a machine is lent (``--out results/{device}-run16-update.json``) names the card that
    measured it."""
    if "{device}" not in str(path):
        return str(path)
    device = jax.devices()[0]
    return str(path).replace("{device}", device_tag(device.device_kind, device.platform))


def write_json(path: str, payload: dict) -> str:
    """Writes ``payload`` atomically (temp file + rename), creating folders; ``{device}`` in ``path`` is expanded
    (:func:`expand_device`). Returns the path written."""
    path = expand_device(path)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=2)
    os.replace(tmp, path)
    return path


def default_out(name: str) -> str:
    kind = jax.devices()[0].device_kind.lower().replace(" ", "-")
    return os.path.join(os.path.dirname(__file__), "results", f"{name}-{kind}.json")
