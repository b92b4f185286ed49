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


def scoped_update(w, x):
    """A toy update with the profile's named scopes: a scanned recurrence under a gradient, then an optimiser."""
    import jax
    import jax.numpy as jnp

    def loss(w):
        with jax.named_scope("encoder_window"):
            _, hs = jax.lax.scan(lambda h, xi: (jnp.tanh(h @ w + xi),) * 2, x[0], x)
        with jax.named_scope("model_losses"):
            return jnp.sum(hs ** 2)

    with jax.named_scope("world_model_grad"):
        grad = jax.grad(loss)(w)
    with jax.named_scope("model_optimizer"):
        return w - 0.1 * grad


def test_scope_labels_from_a_compiled_programs_hlo():
    import jax
    import jax.numpy as jnp

    compiled = jax.jit(jax.vmap(scoped_update)).lower(jnp.ones((3, 4, 4)), jnp.ones((3, 5, 2, 4))).compile()
    op_names = pu.hlo_op_names(compiled.as_text())
    labels = {pu.scope_label(op) for op in op_names.values()}
    # the scan's loop forward and its transpose, the loss, the optimiser step; innermost scope wins
    assert {"encoder_window forward", "encoder_window backward", "model_optimizer forward"} <= labels
    assert not any(label.startswith("world_model_grad") and "while" in op
                   for op, label in ((op, pu.scope_label(op)) for op in op_names.values()))
    assert all("." not in name and "-" not in name for name in op_names)  # keyed as trace kernels name them
    assert pu.scope_label(None) == "unknown" and pu.scope_label("jit(f)/add") == "unscoped"
    assert pu.scope_label("jit(f)/vmap(policy_grad)/transpose(jvp(model_losses))/mul") == "model_losses backward"


def test_summary_by_scope_matches_kernels_by_name_or_hlo_op():
    op_names = {"loop_fusion": "jit(u)/world_model_grad/jvp(encoder_window)/while/body/add",
                "custom_call_3": "jit(u)/world_model_grad/transpose(jvp(encoder_window))/dot_general"}
    events = gpu_trace()
    events[6] = {**events[6], "args": {"hlo_op": "custom-call.3"}}  # the first cutlass_gemm ran custom-call.3
    summary = pu.summarize_kernels(events, calls=2, wall_s=[0.05, 0.03], op_names=op_names)
    assert summary["by_scope"] == {
        "encoder_window forward": {"kernels_per_call": 1.0, "ms_per_call": pytest.approx((10 + 4) / 1e3 / 2)},
        "unknown": {"kernels_per_call": 1.0, "ms_per_call": pytest.approx((2 + 10) / 1e3 / 2)},
        "encoder_window backward": {"kernels_per_call": 0.5, "ms_per_call": pytest.approx(10 / 1e3 / 2)},
    }
    top = {row["name"]: row for row in summary["top_kernels"]}
    assert top["loop_fusion"]["op_name"] == op_names["loop_fusion"]
    assert top["loop_fusion"]["scope"] == "encoder_window forward"
    # cutlass_gemm's first launch ran custom-call.3; its second matched nothing, which does not erase the name
    assert top["cutlass_gemm"]["op_name"] == op_names["custom_call_3"]
    assert top["Memcpy DtoD"]["op_name"] is None and top["Memcpy DtoD"]["scope"] == "unknown"
    plain = pu.summarize_kernels(gpu_trace(), calls=2, wall_s=[0.05, 0.03])
    assert "by_scope" not in plain and "op_name" not in plain["top_kernels"][0]


def test_the_liquid_update_carries_every_scope_the_profile_sums():
    """Each name of ``SCOPES`` labels ops of a (small) cfc-zp-det update, burn-in and window both ways: renaming
    a scope in the agent without the profile (or the reverse) fails here."""
    import jax
    from train_throughput import build_loop

    loop = build_loop("cartpole-balance", "cfc-zp-det", 1, True, {})
    keys = jax.random.split(jax.random.key(0), 1)
    ts = jax.eval_shape(jax.vmap(loop.init), keys)  # shapes suffice: the HLO before XLA's passes names the scopes
    hlo = jax.jit(jax.vmap(loop._update)).lower(ts, keys).as_text(dialect="hlo", debug_info=True)
    labels = {pu.scope_label(op) for op in pu.hlo_op_names(hlo).values()}
    assert {label.rsplit(" ", 1)[0] for label in labels} >= set(pu.SCOPES)
    assert {"encoder_window forward", "encoder_window backward", "encoder_burn_in forward"} <= labels
    assert "encoder_burn_in backward" not in labels  # the burn-in runs under stop_gradient


BACK = 'metadata={op_name="jit(u)/transpose(jvp(encoder_window))/while/body/'  # a scan's backward loop
OPT = 'metadata={op_name="jit(u)/model_optimizer/'
HLO = '''HloModule jit_update

%fused_add (p0: f32[4]) -> f32[4] {
  %p0 = f32[4]{0} parameter(0)
  ROOT %add.1 = f32[4]{0} add(f32[4]{0} %p0, f32[4]{0} %p0), metadata={op_name="jit(u)/model_losses/add"}
}

%body (state: (s32[], f32[4])) -> (s32[], f32[4]) {
  %state = (s32[], f32[4]{0}) parameter(0)
  %h = f32[4]{0} get-tuple-element((s32[], f32[4]{0}) %state), index=1
  %loop_add_fusion.2 = f32[4]{0} fusion(f32[4]{0} %h), kind=kLoop, calls=%fused_add, BACKadd"}
  %copy.3 = f32[4]{0} copy(f32[4]{0} %loop_add_fusion.2), BACKcopy"}
  ROOT %tuple.1 = (s32[], f32[4]{0}) tuple(s32[] %i, f32[4]{0} %copy.3)
}

ENTRY %main (x: f32[4]) -> f32[4] {
  %x = f32[4]{0} parameter(0)
  %while.1 = (s32[], f32[4]{0}) while((s32[], f32[4]{0}) %init), condition=%cond, body=%body
  %custom-call.3 = f32[4]{0} custom-call(f32[4]{0} %x), custom_call_target="gemm", OPTdot_general"}
  ROOT %multiply_fusion = f32[4]{0} fusion(f32[4]{0} %x), kind=kLoop, calls=%fused_add
}
'''.replace("BACK", BACK).replace("OPT", OPT)


def test_launched_ops_counts_entry_and_loop_bodies_but_not_fused_computations():
    import update_kernels as uk

    counts = uk.launched_ops(HLO)
    # the loop body's fusion and copy, the entry's custom call and fusion; not the fused add, not the while,
    # parameters, get-tuple-element or tuple
    assert counts["by_kind"] == {"fusion": 2, "copy": 1, "custom-call": 1}
    assert counts["ops"] == 4
    assert counts["by_scope"] == {"encoder_window backward": 2, "model_optimizer forward": 1, "unknown": 1}
    op_names = pu.hlo_op_names(HLO)
    assert op_names["loop_add_fusion_2"].endswith("while/body/add") and "custom_call_3" in op_names
