"""Prints a Markdown table of the medians in benchmarks/results/*.json and plots environment throughput.

    python benchmarks/summarize.py > benchmarks/results/SUMMARY.md   # also writes env_throughput.png there
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import sys

from lnnmpc.train.png import save_png

RESULTS = os.path.join(os.path.dirname(__file__), "results")


def _options(record: dict) -> str:
    options = {k: v for k, v in record.get("physics_options", {}).items() if v not in (None, False)}
    return ", ".join(f"{k}={v}" for k, v in options.items()) or "dm_control"


def _ms(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


def _with_in_scan(record: dict, part: str) -> str:
    """``record[part_ms]``, followed by ``(in-scan ms)`` where the record timed the part inside a scan."""
    value = _ms(record.get(f"{part}_ms"))
    in_scan = record.get(f"{part}_in_scan_ms")
    return value if in_scan is None else f"{value} ({in_scan:.2f})"


def _setting(payload: dict, task: str, agent: str) -> str:
    """What a training benchmark of ``agent`` on ``task`` changed from the defaults: matmul precision, ``--set``
    overrides that differ from the agent's task defaults (the walker defaults of the LNN agents), the task
    defaults a record did not set (the benchmarks build the agent from ``--set`` alone, so a record made before a
    default was added ran without it: "no rollout_stride=3"), XLA flags; "" for none."""
    from lnnmpc.agents.registry import task_default_overrides
    from lnnmpc.train.config import parse_overrides

    args, parts = payload.get("args", {}), []
    if args.get("matmul_precision", "default") != "default":
        parts.append(f"{args['matmul_precision']} products")
    defaults = task_default_overrides(agent, task)
    given = parse_overrides(list(args.get("overrides") or []))
    for item in args.get("overrides") or []:
        ((key, value),) = parse_overrides([item]).items()
        if key not in defaults or defaults[key] != value:
            parts.append(item)
    parts += [f"no {key}={value:g}" if isinstance(value, float) else f"no {key}={value}"
              for key, value in defaults.items() if key not in given]
    if payload["env"].get("xla_flags"):
        parts.append(f"XLA_FLAGS `{payload['env']['xla_flags']}`")
    return f" ({'; '.join(parts)})" if parts else ""


def _top_scopes(record: dict, count: int = 4) -> str:
    """The `count` named scopes of a profiled program with the most kernel time ("model_losses backward 3.99 ms,
    ..."), or "—" for a record profiled before scopes were recorded."""
    scopes = record.get("by_scope")
    if not scopes:
        return "—"
    ranked = sorted(scopes.items(), key=lambda item: -item[1]["ms_per_call"])[:count]
    return ", ".join(f"{name} {entry['ms_per_call']:.2f} ms" for name, entry in ranked)


def plot_env_throughput(path: str) -> None:
    """ms per agent step versus batch, one line per (domain, solver setting), log-log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines: dict[tuple[str, str], dict[int, float]] = {}
    for file in sorted(glob.glob(os.path.join(RESULTS, "*.json"))):
        with open(file) as f:
            payload = json.load(f)
        if payload.get("benchmark") != "env_throughput" or "command_buffer" in payload["env"].get("xla_flags", ""):
            continue
        for r in payload["results"]:
            options = r.get("physics_options", {})
            label = "exact" if not any(v not in (None, False) for v in options.values()) else (
                f"Newton {options.get('iterations')}/{options.get('ls_iterations')}"
                + (" unrolled" if options.get("unrolled_solver") else "")
                + (" no eulerdamp" if options.get("disable_eulerdamp") else "")
                + (f" contacts<={options['max_contact_points']}" if options.get("max_contact_points") else "")
            )
            lines.setdefault((r["domain"], label), {})[r["batch"]] = r["ms_per_agent_step"]
    from lnnmpc.envs.physics import FAST_PROFILES

    fig, ax = plt.subplots(figsize=(9, 6))
    colors = plt.get_cmap("tab20").colors
    for i, ((domain, label), points) in enumerate(sorted(lines.items())):
        batches = sorted(points)
        fast = FAST_PROFILES[domain]
        is_default = label == f"Newton {fast.iterations}/{fast.ls_iterations}" + (
            " unrolled" if fast.unrolled_solver else "")
        style = "-" if domain == "walker" else "--" if domain == "cartpole" else ":"
        ax.plot(batches, [points[b] for b in batches], style, marker="o", color=colors[i % len(colors)],
                linewidth=3 if is_default else 1.2,
                label=f"{domain}: {label}" + (" (fast default)" if is_default else ""))
    ax.set(xscale="log", yscale="log", xlabel="environments (vmap batch)", ylabel="ms per agent step",
           title="MJX environment step cost on one H100 (action repeat 2)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    save_png(fig, path, dpi=120)


def main() -> None:
    env_rows, cell_rows, train_rows, profile_rows = [], [], [], []
    for path in sorted(glob.glob(os.path.join(RESULTS, "*.json"))):
        with open(path) as f:
            payload = json.load(f)
        name = os.path.basename(path)
        if payload.get("benchmark") == "env_throughput":
            device = payload["env"]["device"]
            flags = "command buffers" if "command_buffer" in payload["env"].get("xla_flags", "") else ""
            for r in payload["results"]:
                env_rows.append(
                    f"| {r['domain']} | {r['profile']} ({_options(r)}) {flags} | {r['batch']} | "
                    f"{r['ms_per_agent_step']:.2f} | {r['agent_steps_per_s']:,.0f} | {device} | {name} |"
                )
        elif payload.get("benchmark") == "train_throughput":
            device = payload["env"]["device"]
            for r in payload["results"]:
                suffix = _setting(payload, r["task"], r["agent"])
                chunk = (f"{r['ms_per_iteration']:.2f} | {r['chunk_env_steps_per_s']:,.0f}" if "ms_per_iteration" in r
                         else "— | —")
                train_rows.append(
                    f"| {r['task']} | {r['agent']}{suffix} | {r['seeds']} | {r['envs']} | {_with_in_scan(r, 'act')} | "
                    f"{_with_in_scan(r, 'env')} | {_with_in_scan(r, 'update')} | {chunk} | {device} | {name} |")
        elif payload.get("benchmark") == "profile_update":
            args = payload.get("args", {})
            for program, r in payload["results"].items():
                categories = ", ".join(f"{k} {v['kernels_per_call']:.0f} / {v['ms_per_call']:.2f} ms"
                                       for k, v in r["by_category"].items() if v["kernels_per_call"] >= 1)
                setting = _setting(payload, args["task"], args["agent"])
                profile_rows.append(
                    f"| {args['task']} | {args['agent']}{setting} | {args.get('seeds')} | {program} | "
                    f"{r['wall_ms_per_call']:.2f} | {r['busy_ms_per_call']:.2f} | {r['busy_fraction']:.2f} | "
                    f"{r['kernels_per_call']:.0f} | {categories} | {_top_scopes(r)} | {payload['env']['device']} | "
                    f"{name} |")
        elif "results" in payload and payload["results"] and "forward_backward_ms_median" in payload["results"][0]:
            for r in payload["results"]:
                peak = r.get("peak_bytes_in_use")
                cell_rows.append(
                    f"| {r['cell']} | {r['seeds']} | {r['forward_backward_ms_median']:.3f} | "
                    f"{r['forward_ms_median']:.3f} | {peak / 2**20 if peak else float('nan'):.0f} | "
                    f"{r['device']['kind']} | {name} |"
                )
    print("# Benchmark medians\n\nGenerated by `python benchmarks/summarize.py` from the JSON files here.\n")
    print("## Environment throughput (action repeat 2, random actions, `vmap` batch, `lax.scan` of agent steps)\n")
    print("| domain | profile (solver settings) | batch | ms / agent step | agent steps / s | device | file |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(env_rows))
    print("\n## Liquid cells: 42-step unroll, B=256, input 30, hidden 64, CfC backbone 192, forward+backward\n")
    print("| variant | seeds (vmap) | fwd+bwd ms | fwd ms | peak MiB | device | file |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(cell_rows))
    print("\n## Training steps (benchmarks/train_throughput.py): act, env step, one update, end-to-end chunk\n")
    print("A standalone call's time; in parentheses, where measured (`--in-scan N`), the time per call when N of them "
          "run inside one `lax.scan`, as the training chunk runs them.\n")
    print("| task | agent | seeds | envs | act ms | env ms | update ms | chunk ms / iteration | chunk env steps / s "
          "| device | file |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(train_rows))
    print("\n## Where an update's time goes (benchmarks/profile_update.py): kernels of a traced call\n")
    print("| task | agent | seeds | program | wall ms | busy ms | busy fraction | kernels / call | by category "
          "(kernels / ms per call) | largest named scopes (kernel ms per call) | device | file |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(profile_rows))
    with contextlib.redirect_stdout(sys.stderr):  # what importing matplotlib's plugins prints stays out of the table
        plot_env_throughput(os.path.join(RESULTS, "env_throughput.png"))
    print("\n![env throughput](env_throughput.png)")


if __name__ == "__main__":
    main()
