"""The profile benchmark's trace summary (benchmarks/profile_update.py) on synthetic traces with known answers."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import profile_update as pu  # noqa: E402


def meta(pid, name, tid=None):
    event = {"ph": "M", "pid": pid, "name": "thread_name" if tid is not None else "process_name",
             "args": {"name": name}}
    if tid is not None:
        event["tid"] = tid
    return event


def kernel(pid, tid, name, ts, dur):
    return {"ph": "X", "pid": pid, "tid": tid, "name": name, "ts": ts, "dur": dur}


def test_interval_union_matches_a_unit_grid_reference():
    rng = np.random.default_rng(0)
    for _ in range(50):
        starts = rng.integers(0, 200, size=rng.integers(1, 30))
        intervals = [(int(s), int(s + rng.integers(0, 40))) for s in starts]
        grid = np.zeros(300, dtype=bool)
        for start, end in intervals:
            grid[start:end] = True
        assert pu.interval_union([(float(s), float(e)) for s, e in intervals]) == pytest.approx(grid.sum())


def test_kernel_category_names():
    assert pu.kernel_category("sm90_xmma_gemm_f32f32_tf32f32") == "matmul"
    assert pu.kernel_category("loop_add_fusion_3") == "fusion"
    assert pu.kernel_category("input_reduce_fusion") == "reduce"
    assert pu.kernel_category("Memcpy DtoD") == "copy"
    assert pu.kernel_category("rng_bit_generator") == "other"


def gpu_trace():
    return [
        meta(1, "/device:GPU:0"), meta(1, "Stream #7(Compute)", tid=7), meta(1, "Stream #9(Compute)", tid=9),
        meta(1, "XLA Ops", tid=100), meta(2, "/host:CPU"), meta(2, "python", tid=5),
        # call 1: a gemm overlapping a fusion on another stream, then a copy
        kernel(1, 7, "cutlass_gemm", 0, 10), kernel(1, 9, "loop_fusion", 5, 10), kernel(1, 7, "Memcpy DtoD", 20, 2),
        # call 2
        kernel(1, 7, "cutlass_gemm", 100, 10), kernel(1, 7, "loop_fusion", 110, 4),
        # derived line and host work: not kernels
        kernel(1, 100, "dot.3", 0, 10), kernel(2, 5, "PjitFunction(update)", 0, 200),
    ]


def test_summary_counts_stream_kernels_once_per_call():
    summary = pu.summarize_kernels(gpu_trace(), calls=2, wall_s=[0.05, 0.03])
    assert summary["source"] == "device streams"
    assert summary["kernels_per_call"] == 2.5
    assert summary["distinct_kernels"] == 3
    assert summary["busy_ms_per_call"] == pytest.approx((15 + 2 + 14) / 1e3 / 2)  # overlap counted once
    assert summary["kernel_ms_per_call"] == pytest.approx((10 + 10 + 2 + 10 + 4) / 1e3 / 2)
    assert summary["wall_ms_per_call"] == pytest.approx(40.0)
    assert summary["busy_fraction"] == pytest.approx(summary["busy_ms_per_call"] / 40.0)
    assert summary["by_category"]["matmul"] == {"kernels_per_call": 1.0, "ms_per_call": pytest.approx(0.010)}
    assert summary["top_kernels"][0]["name"] == "cutlass_gemm"
    assert summary["top_kernels"][0]["mean_us"] == 10.0
    assert [row["name"] for row in summary["top_kernels"]] == ["cutlass_gemm", "loop_fusion", "Memcpy DtoD"]


def test_host_only_trace_falls_back_to_the_executor_threads():
    events = [meta(2, "/host:CPU"), meta(2, "python", tid=5), meta(2, "tf_XLAPjRtCpuClient/1", tid=6),
              kernel(2, 5, "PjitFunction(update)", 0, 100), kernel(2, 6, "ynn_fusion", 10, 30)]
    summary = pu.summarize_kernels(events, calls=1, wall_s=[1e-4])
    assert summary["source"] == "host executor threads"
    assert summary["kernels_per_call"] == 1 and summary["busy_ms_per_call"] == pytest.approx(0.030)


def test_profile_call_traces_a_jitted_function_on_this_machine():
    import jax
    import jax.numpy as jnp

    fn = jax.jit(lambda x: jnp.tanh(x @ x).sum())
    summary = pu.profile_call(fn, (jnp.ones((32, 32)),), calls=2, warmup=1, top=5)
    assert summary["calls"] == 2 and summary["kernels_per_call"] >= 1
    assert 0 < summary["busy_ms_per_call"] and summary["wall_ms_per_call"] > 0
    assert summary["processes"] and len(summary["top_kernels"]) <= 5
