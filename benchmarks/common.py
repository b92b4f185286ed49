"""Helpers shared by the benchmarks: environment metadata, timing with medians, JSON output."""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from importlib import metadata

import jax


def environment_info() -> dict:
    """Device and package versions, recorded in every benchmark JSON."""
    device = jax.devices()[0]
    versions = {}
    for package in ("jax", "jaxlib", "flax", "optax", "mujoco", "mujoco-mjx", "dm-control"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    return {
        "device": device.device_kind,
        "platform": device.platform,
        "device_count": jax.device_count(),
        "python": platform.python_version(),
        "versions": versions,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def time_call(fn, *args, repeats: int = 5) -> dict:
    """Compiles/warms ``fn`` once, then times ``repeats`` calls; seconds, median first."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return {"median_s": statistics.median(times), "min_s": min(times), "times_s": times, "first_call_s": first}


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


def write_json(path: str, payload: dict) -> None:
    """Writes ``payload`` atomically (temp file + rename), creating folders."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=2)
    os.replace(tmp, path)


def default_out(name: str) -> str:
    kind = jax.devices()[0].device_kind.lower().replace(" ", "-")
    return os.path.join(os.path.dirname(__file__), "results", f"{name}-{kind}.json")
