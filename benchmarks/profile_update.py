"""Where one update (or act step) spends its time on the device: a `jax.profiler` trace of a few calls, summed per
kernel, with the device's busy time set against the wall time of a call.

The update is latency-bound (``benchmarks/results/README.md``: 13.5 TFLOP/s, unchanged by bfloat16 products), so
the question is whether the time goes to gaps between many short kernels (cut their number: fusion, fewer scan
steps, command buffers) or to a few long ones (make those faster). Per program it records:

* ``kernels_per_call``: kernel launches on the device per call (each step of a ``lax.scan`` launches its own);
* ``busy_ms_per_call``: the union of the kernels' intervals per call, against ``wall_ms_per_call`` (host clock,
  dispatch to ready); ``busy_fraction`` = busy / wall: low means launch gaps dominate;
* ``by_category``: matmul / fusion / reduce / copy / other kernels (count and time per call);
* ``top_kernels``: the kernels with the most time per call (name, launches and µs per call, mean µs; for a
  compiled program also the ``op_name`` of the jax operation it ran and its scope, to tell which layer or
  transpose a long kernel belongs to);
* ``by_scope``: kernels and time per call by the update's named scopes (``SCOPES``: replay sample, encoder
  burn-in and window, TD targets, model losses, optimisers, ...), forward and backward apart, from the
  ``op_name`` of the HLO instruction each kernel ran.

``--what burst`` profiles ``--burst`` updates run in one ``lax.scan`` (``TrainingLoop.update_burst``), as the
training chunk runs them, with every figure per update: a standalone call of the update also pays for its
dispatch and per-call set-up, which the chunk does not (``train_throughput.py --in-scan``).

On a machine without an accelerator the trace has no device, and the XLA executor threads of the host stand in
(their ops rather than kernels), which is enough to check the script.

    python benchmarks/profile_update.py --task walker-run --agent cfc-zp-det --seeds 3 \\
        --set input_transform=symlog --set lambda_=0 --set rollout_steps=3
    python benchmarks/profile_update.py --small --task cartpole-balance --calls 2 --out /tmp/p.json   # CPU check
    python benchmarks/profile_update.py ... --what burst --burst 16   # the update as the training chunk runs it
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import sys
import tempfile
import time

import jax

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import default_out, environment_info, write_json  # noqa: E402
from train_throughput import act_call, build_loop, filled_state, update_burst_program, update_call  # noqa: E402

from lnnmpc.train.config import parse_overrides  # noqa: E402

CATEGORIES = (  # first match wins; names of cuBLAS/cuDNN/CUTLASS products and XLA's own kernels
    ("matmul", ("gemm", "cublas", "cutlass", "xmma", "nvjet", "dot", "triton_gemm")),
    ("copy", ("memcpy", "memset", "copy", "transpose")),
    ("reduce", ("reduce", "reduction")),
    ("fusion", ("fusion",)),
)
HOST_EXECUTOR_THREADS = ("XLA", "Xla", "xla")  # thread-name markers of the CPU client's executor threads
# The named scopes of the update (loop._update, TDMPC2.update, LNNTDMPC2's loss), innermost found wins.
SCOPES = ("replay_sample", "keep_if_valid", "world_model_grad", "encoder_burn_in", "encoder_window", "td_targets",
          "model_losses", "model_optimizer", "policy_grad", "policy_optimizer")
_INSTRUCTION = re.compile(r'^\s*(?:ROOT )?%?([\w.\-]+) = [^\n]*?metadata=\{[^}]*op_name="([^"]+)"', re.M)


def kernel_category(name: str) -> str:
    """matmul / copy / reduce / fusion / other, from a kernel's name."""
    lower = name.lower()
    for category, markers in CATEGORIES:
        if any(marker in lower for marker in markers):
            return category
    return "other"


def trace_name(instruction: str) -> str:
    """The name a kernel of an HLO instruction carries in a trace: dots and dashes as underscores
    (``loop_add_fusion.2`` -> ``loop_add_fusion_2``)."""
    return re.sub(r"[.\-]", "_", instruction)


def hlo_op_names(hlo_text: str) -> dict[str, str]:
    """Each instruction of a compiled HLO module (``compiled.as_text()``) with its ``op_name`` metadata, keyed by
    :func:`trace_name`."""
    return {trace_name(name): op_name for name, op_name in _INSTRUCTION.findall(hlo_text)}


def scope_label(op_name: str | None) -> str:
    """``"<innermost of SCOPES> forward|backward"`` for an op's ``op_name`` (backward: under a ``transpose``),
    ``"unscoped"`` for an op outside them, ``"unknown"`` for a kernel that matched no instruction."""
    if op_name is None:
        return "unknown"
    found = [word for word in re.findall(r"\w+", op_name) if word in SCOPES]
    if not found:
        return "unscoped"
    return f"{found[-1]} {'backward' if 'transpose(' in op_name else 'forward'}"


def interval_union(intervals: list[tuple[float, float]]) -> float:
    """Total length covered by ``(start, end)`` intervals (overlaps counted once)."""
    total, current_start, current_end = 0.0, None, None
    for start, end in sorted(intervals):
        if current_end is None or start > current_end:
            if current_end is not None:
                total += current_end - current_start
            current_start, current_end = start, end
        else:
            current_end = max(current_end, end)
    if current_end is not None:
        total += current_end - current_start
    return total


def _metadata(events: list[dict], kind: str) -> list[dict]:
    """The trace's metadata ("M") events of one kind (``process_name``, ``thread_name``)."""
    return [e for e in events if e.get("ph") == "M" and e.get("name") == kind]


def kernel_events(events: list[dict]) -> tuple[list[dict], str]:
    """The complete ("X") events of the device processes (names starting ``/device:``; of their ``Stream``
    threads where there are such), else, on a host-only trace, those of the XLA executor threads; with which
    of these it found."""
    names = {e["pid"]: e["args"]["name"] for e in _metadata(events, "process_name")}
    threads = {(e["pid"], e.get("tid")): e["args"]["name"] for e in _metadata(events, "thread_name")}
    device_pids = {pid for pid, name in names.items() if name.startswith("/device:")}
    complete = [e for e in events if e.get("ph") == "X" and "dur" in e]
    found = [e for e in complete if e["pid"] in device_pids]
    # Kernels run on the device's streams; lines derived from them ("XLA Ops", "XLA Modules") would count twice.
    streams = [e for e in found if threads.get((e["pid"], e.get("tid")), "").startswith("Stream")]
    if streams or found:
        return streams or found, "device streams" if streams else "device"
    executor = {key for key, name in threads.items() if any(m in name for m in HOST_EXECUTOR_THREADS)}
    return [e for e in complete if (e["pid"], e.get("tid")) in executor], "host executor threads"


def kernel_op_name(event: dict, op_names: dict[str, str]) -> str | None:
    """The ``op_name`` of the instruction a kernel event ran: by the event's ``hlo_op`` argument where the trace
    gives one (library kernels such as cuBLAS's), else by its own name (XLA's kernels are named after it)."""
    for name in (event.get("args", {}).get("hlo_op"), event["name"]):
        if name and (op_name := op_names.get(trace_name(name))) is not None:
            return op_name
    return None


def summarize_kernels(events: list[dict], calls: int, wall_s: list[float], top: int = 25,
                      op_names: dict[str, str] | None = None) -> dict:
    """Per-call totals of a trace's kernels (``kernel_events``) over ``calls`` calls timed at ``wall_s``; with
    ``op_names`` (:func:`hlo_op_names` of the program) also per named scope of the update (``by_scope``)."""
    kernels, source = kernel_events(events)
    per_name = collections.defaultdict(lambda: [0, 0.0])
    per_category = collections.defaultdict(lambda: [0, 0.0])
    per_scope = collections.defaultdict(lambda: [0, 0.0])
    name_op = {}  # kernel name -> the op_name of the first of its launches that matched an instruction
    for e in kernels:
        per_name[e["name"]][0] += 1
        per_name[e["name"]][1] += e["dur"]
        op_name = kernel_op_name(e, op_names or {})
        if op_name is not None:
            name_op.setdefault(e["name"], op_name)
        for table, key in ((per_category, kernel_category(e["name"])), (per_scope, scope_label(op_name))):
            table[key][0] += 1
            table[key][1] += e["dur"]
    busy_us = interval_union([(e["ts"], e["ts"] + e["dur"]) for e in kernels])
    wall_ms = 1e3 * sum(wall_s) / len(wall_s)
    busy_ms = busy_us / 1e3 / calls
    ranked = sorted(per_name.items(), key=lambda item: -item[1][1])[:top]
    return {
        "source": source,
        # What the trace held, to see why a device was not found where one was expected.
        "processes": sorted({e["args"]["name"] for e in _metadata(events, "process_name")}),
        "calls": calls,
        "kernels_per_call": len(kernels) / calls,
        "distinct_kernels": len(per_name),
        "busy_ms_per_call": busy_ms,
        "kernel_ms_per_call": sum(e["dur"] for e in kernels) / 1e3 / calls,
        "wall_ms_per_call": wall_ms,
        "busy_fraction": busy_ms / wall_ms if wall_ms > 0 else None,
        "by_category": {name: {"kernels_per_call": n / calls, "ms_per_call": us / 1e3 / calls}
                        for name, (n, us) in sorted(per_category.items(), key=lambda item: -item[1][1])},
        # with op_names, each also with the jax op it ran (``op_name``: which layer, which transpose) and its scope
        "top_kernels": [{"name": name, "launches_per_call": n / calls, "us_per_call": us / calls, "mean_us": us / n,
                         **({"op_name": name_op.get(name), "scope": scope_label(name_op.get(name))}
                            if op_names else {})}
                        for name, (n, us) in ranked],
        **({"by_scope": {name: {"kernels_per_call": n / calls, "ms_per_call": us / 1e3 / calls}
                         for name, (n, us) in sorted(per_scope.items(), key=lambda item: -item[1][1])}}
           if op_names else {}),
    }


def load_trace(directory: str) -> list[dict]:
    """The events of the newest perfetto trace (``*perfetto_trace.json.gz``) under ``directory``."""
    paths = sorted(glob.glob(os.path.join(directory, "**", "*perfetto_trace.json.gz"), recursive=True),
                   key=os.path.getmtime)
    if not paths:
        raise FileNotFoundError(f"no perfetto_trace.json.gz under {directory}: did jax.profiler write one?")
    with gzip.open(paths[-1], "rt") as f:
        data = json.load(f)
    return data["traceEvents"] if isinstance(data, dict) else data


def profile_call(fn, args: tuple, calls: int, warmup: int = 2, top: int = 25, per_call: int = 1) -> dict:
    """Warms ``fn(*args)`` up, traces ``calls`` calls (each waited for) and summarizes the trace's kernels, by
    named scope too where ``fn`` is compiled (``jax.jit(f).lower(...).compile()``: its HLO names the scopes).
    ``per_call``: how many units of work one call does (a burst of updates in one scan); every per-call figure
    is then per unit."""
    for _ in range(warmup):
        jax.block_until_ready(fn(*args))
    wall = []
    with tempfile.TemporaryDirectory() as directory:
        with jax.profiler.trace(directory, create_perfetto_trace=True):
            for _ in range(calls):
                start = time.perf_counter()
                jax.block_until_ready(fn(*args))
                wall.append(time.perf_counter() - start)
        events = load_trace(directory)
    op_names = hlo_op_names(fn.as_text()) if hasattr(fn, "as_text") else None  # a compiled program's HLO
    return summarize_kernels(events, calls * per_call, [w / per_call for w in wall], top, op_names=op_names)


def programs(args) -> tuple[dict, bool]:
    """The compiled programs to profile, each as (function, arguments, units of work per call): the agent's
    update and act step, vmapped over seeds (act also over environments), and ``--burst`` updates in one scan
    (``TrainingLoop.update_burst``, as the training chunk runs them), on a replay filled with random steps; and
    whether the update keeps its empty-replay guard (``LoopConfig.guard_empty_replay``)."""
    loop = build_loop(args.task, args.agent, args.envs, args.small, parse_overrides(args.overrides),
                      fill=None if args.keep_replay_guard else args.fill)
    ts = filled_state(loop, args.seeds, args.fill)
    out = {}
    if "update" in args.what:
        out["update"] = (*update_call(loop, ts), 1)
    if "act" in args.what:
        act, act_args = act_call(loop.agent, ts)
        out["act"] = act.lower(*act_args).compile(), act_args, 1
    if "burst" in args.what:
        out["burst"] = update_burst_program(loop).lower(ts, args.burst).compile(), (ts,), args.burst
    return out, loop.config.guard_empty_replay


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="walker-run")
    parser.add_argument("--agent", default="cfc-zp-det")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--envs", type=int, default=1, help="environments per seed (the act step's batch)")
    parser.add_argument("--what", default="update,act",
                        help="programs to profile: update, act, burst (comma list)")
    parser.add_argument("--burst", type=int, default=16,
                        help="updates per call of the burst program (one lax.scan); its figures are per update")
    parser.add_argument("--calls", type=int, default=5, help="calls traced per program")
    parser.add_argument("--fill", type=int, default=600, help="random iterations to fill the replay first")
    parser.add_argument("--top", type=int, default=25, help="kernels listed per program")
    parser.add_argument("--small", action="store_true", help="tiny networks and planner (CPU check)")
    parser.add_argument("--keep-replay-guard", action="store_true",
                        help="keep the update's empty-replay guard the trainer drops after a long enough seed phase")
    parser.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE",
                        help="agent hyperparameter override, repeatable (e.g. --set rollout_steps=3)")
    parser.add_argument("--out", default=None, help="JSON path; {device} in it becomes h100, h200, cpu, ...")
    args = parser.parse_args(argv)
    unknown = set(args.what.split(",")) - {"update", "act", "burst"}
    if unknown:
        parser.error(f"unknown --what {sorted(unknown)}: choose from update, act, burst")
    if min(args.calls, args.seeds, args.envs, args.burst) < 1:
        parser.error(f"--calls, --seeds, --envs and --burst must be >= 1 "
                     f"(got {args.calls}, {args.seeds}, {args.envs}, {args.burst})")
    out = args.out or default_out(f"profile-{args.agent}-{args.task}")
    payload = {"benchmark": "profile_update", "env": environment_info(), "args": vars(args), "results": {}}
    compiled, payload["guard_empty_replay"] = programs(args)
    for name, (fn, fn_args, per_call) in compiled.items():
        summary = profile_call(fn, fn_args, args.calls, top=args.top, per_call=per_call)
        payload["results"][name] = summary
        out = write_json(out, payload)
        print(f"{name:6s} {summary['wall_ms_per_call']:8.2f} ms wall  {summary['busy_ms_per_call']:8.2f} ms busy "
              f"({summary['source']})  {summary['kernels_per_call']:7.0f} kernels/call", flush=True)
        for category, row in summary["by_category"].items():
            print(f"    {category:8s} {row['kernels_per_call']:7.0f} kernels  {row['ms_per_call']:8.3f} ms", flush=True)
        for scope, row in summary.get("by_scope", {}).items():
            print(f"    {scope:28s} {row['kernels_per_call']:7.0f} kernels  {row['ms_per_call']:8.3f} ms", flush=True)
        for row in summary["top_kernels"][:10]:
            print(f"    {row['us_per_call']:9.1f} us  x{row['launches_per_call']:<6.0f} {row['name'][:90]}", flush=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
