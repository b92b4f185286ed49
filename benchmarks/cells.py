"""Forward+backward time and peak memory of CfC / LTC sequence unrolls, for 1 seed and several seeds under vmap.

Defaults are the sizes of issue #3: a 42-step unroll, batch 256, input 30, hidden 64, CfC backbone 192 units
(one layer), LTC fully connected with 6 ODE unfolds; 1 and 8 seeds. ``cfc`` is the default (fused) unroll:
input projection hoisted out of the scan, one head matmul, custom VJP with hoisted weight gradients;
``cfc-step`` scans ``CfCCell.apply`` step by step (the previous path). LTC variants: ``ltc`` (sensory
currents of all steps computed before the scan, JAX autodiff of the sub-steps with the synaptic activations
recomputed in the backward pass: ``LTCCell(manual_backward=False)``),
``ltc-step`` (sensory currents per step, the previous path), ``ltc-remat`` (plus ``jax.checkpoint`` per time
step), ``ltc-stored`` (``recompute_synapses=False``: stores B*H*H activations per sub-step; ~40 GB at 8 seeds),
``ltc-vjp`` (``LTCCell(manual_backward=True)``, the default cell: hand-derived backward that recomputes the
synaptic sigmoids inside fused reductions and writes no B*H*H tensor). ``*-unrollN`` variants
(``cfc-unroll2``, ``ltc-unroll2``, ``ltc-vjp-unroll2``, ...) use ``lax.scan(unroll=N)`` whatever
``--scan-unroll`` says, so one run compares them.
Each configuration runs in its own Python process so that the peak-memory counter of the device
(``jax.devices()[0].memory_stats()['peak_bytes_in_use']``, None where the backend has no counter, e.g. CPU)
belongs to that configuration alone. Compilation is excluded; each timing blocks until the result is ready.

    python benchmarks/cells.py                   # issue sizes, writes benchmarks/results/cells-<device>.json
    python benchmarks/cells.py --small --out /tmp/cells.json   # tiny shapes, a quick check on CPU
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

ISSUE_SIZES = {"length": 42, "batch": 256, "inputs": 30, "hidden": 64, "backbone_units": 192}
SMALL_SIZES = {"length": 8, "batch": 16, "inputs": 6, "hidden": 8, "backbone_units": 16}
TARGETS_H100 = {"cfc_ms": 2.5, "ltc_ms": 15.0, "seeds_ratio": 1.6}
RESET_PROBABILITY = 0.02
MAX_DT = 2.0
# variant: (cell kind, unroll(fused=...), unroll(remat=...), LTC recompute_synapses, LTC manual_backward,
#          lax.scan unroll or None for --scan-unroll)
VARIANT_FIELDS = ("cell", "fused", "remat", "recompute_synapses", "manual_backward", "scan_unroll")
VARIANTS = {
    "cfc": ("cfc", True, False, None, None, None),
    "cfc-unroll2": ("cfc", True, False, None, None, 2),
    "cfc-unroll4": ("cfc", True, False, None, None, 4),
    "cfc-step": ("cfc", False, False, None, None, None),
    "ltc": ("ltc", True, False, True, False, None),
    "ltc-vjp": ("ltc", True, False, True, True, None),
    "ltc-vjp-unroll2": ("ltc", True, False, True, True, 2),
    "ltc-unroll2": ("ltc", True, False, True, False, 2),
    "ltc-step": ("ltc", False, False, True, False, None),
    "ltc-remat": ("ltc", True, True, True, False, None),
    "ltc-stored": ("ltc", True, False, False, False, None),
}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--small", action="store_true", help="tiny shapes (CPU smoke run)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON path (default benchmarks/results/cells-<device>.json)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 8], help="seed counts (1 = no vmap)")
    parser.add_argument("--cells", nargs="+", default=["cfc", "cfc-step", "ltc", "ltc-vjp", "ltc-step", "ltc-remat"],
                        choices=list(VARIANTS),
                        help="cell variants (*-step: unfused per-step unroll; ltc-remat: jax.checkpoint per "
                             "step; ltc-stored: recompute_synapses=False, stores the B*H*H activations; "
                             "ltc-vjp: LTCCell(manual_backward=True), hand-derived fused backward; "
                             "*-unrollN: lax.scan unroll=N regardless of --scan-unroll)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls (default 50, small: 5)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed calls after compilation")
    parser.add_argument("--scan-unroll", type=int, default=1,
                        help="time steps per lax.scan iteration (variants named *-unrollN use N instead)")
    parser.add_argument("--worker", type=str, default=None, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def build_cell(variant: str, sizes: dict):
    from lnnmpc.nets import CfCCell, LTCCell

    kind, _, _, recompute_synapses, manual_backward, _ = VARIANTS[variant]
    if kind == "cfc":
        return CfCCell(sizes["hidden"], backbone_units=sizes["backbone_units"], backbone_layers=1)
    return LTCCell(sizes["hidden"], recompute_synapses=recompute_synapses, manual_backward=manual_backward)


def make_batch(key, seeds: int, sizes: dict):
    """Inputs (T, B, I), Δt (T, B) in [0, MAX_DT], resets (T, B); with a leading seed axis when seeds > 1."""
    import jax

    shape = (sizes["length"], sizes["batch"])
    lead = (seeds,) if seeds > 1 else ()
    k_x, k_dt, k_reset = jax.random.split(key, 3)
    inputs = jax.random.normal(k_x, lead + shape + (sizes["inputs"],))
    dts = jax.random.uniform(k_dt, lead + shape, maxval=MAX_DT)
    resets = jax.random.bernoulli(k_reset, RESET_PROBABILITY, lead + shape)
    return inputs, dts, resets


def make_step_functions(cell, sizes: dict, seeds: int, remat: bool, scan_unroll: int, fused: bool = True):
    """Jitted forward and forward+backward functions of (variables, inputs, dts, resets)."""
    import jax
    import jax.numpy as jnp

    from lnnmpc.nets import unroll

    h0 = cell.initial_state(sizes["batch"])

    def loss(variables, inputs, dts, resets):
        result = unroll(cell, variables, h0, inputs, dts, resets, remat=remat, scan_unroll=scan_unroll,
                        fused=fused)
        return jnp.mean(result.states**2) + jnp.mean(result.outputs)

    forward_backward = jax.value_and_grad(loss)
    if seeds > 1:
        loss, forward_backward = jax.vmap(loss), jax.vmap(forward_backward)
    return jax.jit(loss), jax.jit(forward_backward)


def time_calls(function, arguments, warmup: int, repeats: int) -> list[float]:
    """Milliseconds of ``repeats`` calls after ``warmup`` calls, each blocked until ready."""
    import jax

    for _ in range(warmup):
        jax.block_until_ready(function(*arguments))
    timings = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function(*arguments))
        timings.append((time.perf_counter() - start) * 1e3)
    return timings


def compiled_memory(function, arguments) -> dict | None:
    """Compiler's memory estimate (bytes) of a jitted function, when the backend reports one."""
    try:
        analysis = function.lower(*arguments).compile().memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend implements it
        return None
    if analysis is None:
        return None
    fields = ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes")
    return {field: int(getattr(analysis, field)) for field in fields if hasattr(analysis, field)}


def run_worker(spec: dict) -> dict:
    """Measure one (cell variant, seeds) configuration in this process."""
    import jax

    sizes, seeds, variant = spec["sizes"], spec["seeds"], spec["cell"]
    cell = build_cell(variant, sizes)
    key_init, key_batch = jax.random.split(jax.random.PRNGKey(0))
    inputs, dts, resets = make_batch(key_batch, seeds, sizes)
    example = (cell.initial_state(sizes["batch"]), inputs[(0,) * (inputs.ndim - 2)], dts[(0,) * (dts.ndim - 1)])
    if seeds > 1:
        variables = jax.vmap(lambda key: cell.init(key, *example))(jax.random.split(key_init, seeds))
    else:
        variables = cell.init(key_init, *example)
    arguments = (variables, inputs, dts, resets)
    _, fused, remat, _, _, scan_unroll = VARIANTS[variant]
    scan_unroll = spec["scan_unroll"] if scan_unroll is None else scan_unroll
    forward, forward_backward = make_step_functions(cell, sizes, seeds, remat=remat, fused=fused,
                                                    scan_unroll=scan_unroll)
    start = time.perf_counter()
    jax.block_until_ready(forward_backward(*arguments))
    compile_s = time.perf_counter() - start
    fb_times = time_calls(forward_backward, arguments, spec["warmup"], spec["repeats"])
    fwd_times = time_calls(forward, arguments, spec["warmup"], spec["repeats"])
    device = jax.devices()[0]
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    return {
        "cell": variant,
        "seeds": seeds,
        "scan_unroll": scan_unroll,
        "vmap": seeds > 1,
        "forward_backward_ms_median": statistics.median(fb_times),
        "forward_backward_ms_min": min(fb_times),
        "forward_ms_median": statistics.median(fwd_times),
        "first_call_s_incl_compile": compile_s,
        "peak_bytes_in_use": (stats or {}).get("peak_bytes_in_use"),
        "compiled_memory_forward_backward": compiled_memory(forward_backward, arguments),
        "parameters_per_seed": sum(x.size for x in jax.tree.leaves(variables)) // seeds,
        "device": {"platform": device.platform, "kind": device.device_kind},
    }


def device_slug(device: dict) -> str:
    name = device["kind"] if device["platform"] != "cpu" else "cpu"
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def summarise(results: list[dict]) -> dict:
    """Seed-scaling ratios and the issue's H100 targets, for the headline numbers."""
    by_key = {(r["cell"], r["seeds"]): r["forward_backward_ms_median"] for r in results if "error" not in r}
    ratios = {f"{cell}_{seeds}_over_1": by_key[(cell, seeds)] / by_key[(cell, 1)]
              for (cell, seeds) in by_key if seeds > 1 and (cell, 1) in by_key}
    return {"seed_scaling": ratios, "targets_h100": TARGETS_H100}


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.worker is not None:
        print(json.dumps(run_worker(json.loads(args.worker))))
        return
    import flax
    import jax

    sizes = SMALL_SIZES if args.small else ISSUE_SIZES
    repeats = args.repeats or (5 if args.small else 50)
    results = []
    for variant in args.cells:
        for seeds in args.seeds:
            spec = {"cell": variant, "seeds": seeds, "sizes": sizes, "repeats": repeats, "warmup": args.warmup,
                    "scan_unroll": args.scan_unroll}
            completed = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)],
                                       capture_output=True, text=True, check=False)
            if completed.returncode != 0:  # e.g. out of memory: record it and go on
                error = (completed.stderr.strip().splitlines() or ["no output"])[-1]
                results.append({"cell": variant, "seeds": seeds, "error": error})
                print(f"{variant:16s} seeds={seeds}: FAILED {error}")
                continue
            results.append(json.loads(completed.stdout.strip().splitlines()[-1]))
            print(f"{variant:16s} seeds={seeds}: fwd+bwd {results[-1]['forward_backward_ms_median']:.3f} ms "
                  f"(fwd {results[-1]['forward_ms_median']:.3f} ms), peak {results[-1]['peak_bytes_in_use']}")
    measured = [r for r in results if "error" not in r]
    if not measured:
        sys.exit("every configuration failed")
    device = measured[0]["device"]
    report = {
        "benchmark": "liquid cell unroll, forward+backward (jit(value_and_grad)), compile excluded",
        "device": device,
        "versions": {"jax": jax.__version__, "flax": flax.__version__, "python": platform.python_version()},
        "config": {**sizes, "small": args.small, "repeats": repeats, "warmup": args.warmup,
                   "scan_unroll": args.scan_unroll,
                   "variants": {name: dict(zip(VARIANT_FIELDS, spec, strict=True))
                                for name, spec in VARIANTS.items() if name in args.cells},
                   "cfc": "mode=default, 1 backbone layer, lecun_tanh", "ltc": "FullyConnected, 6 unfolds, softplus",
                   "dt": f"U(0, {MAX_DT}) per sample", "reset_probability": RESET_PROBABILITY,
                   "loss": "mean(states^2) + mean(outputs); gradients w.r.t. parameters", "dtype": "float32"},
        "results": results,
        "summary": summarise(results),
    }
    out = args.out or Path(__file__).resolve().parent / "results" / f"cells-{device_slug(device)}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
