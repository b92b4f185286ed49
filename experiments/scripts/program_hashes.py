"""The programs a run trains with, lowered here from its config.json, named by the sha256 of their StableHLO text.

    PYTHONPATH=<checkout>/src python experiments/scripts/program_hashes.py RUN [RUN ...] [--dump DIR] [--scatters]

For each run folder: the training chunk, the seed phase, the update burst and the evaluation, lowered (traced, not
compiled) on this machine's JAX device for the run's recorded settings, each with the first 16 hex digits of the
sha256 of its text. With several runs a last table says, program by program, whether all runs' texts are equal.
Lowering with another checkout's ``src`` on ``PYTHONPATH`` tells whether two commits build the same programs for
one configuration: RESULTS.md [91] found the acrobot recipe's four programs byte-identical at ``0c4e564`` and
``3560bc0``, so its two launches that parted on the GPU had run the same programs. ``--dump DIR`` also writes each
text to ``DIR/<run name>-<program>.txt`` for a diff.

``--scatters`` adds a table of each program's scatters: those that add into their operand over indices not declared
unique (XLA's GPU backend sums colliding updates with atomic adds, in an order that can change from one execution to
the next unless ``--xla_gpu_deterministic_ops`` is set; the CPU's loop sums in order) and the rest. RESULTS.md [92]
counted them for the acrobot recipe: 32 in the seed phase's program (MJX's physics), 1 in the update burst.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import tempfile

PROGRAMS = ("train_chunk", "seed_chunk", "update_burst", "evaluate")


def lowered_programs(run: str) -> dict[str, str]:
    """{program: StableHLO text} of run folder ``run``'s programs (:data:`PROGRAMS`), lowered for one placement of
    its seeds on this machine's first device(s), as the trainer lowers them; nothing is compiled or written."""
    import jax

    from lnnmpc.train import runfolder
    from lnnmpc.train.config import TrainConfig
    from lnnmpc.train.setup import validate
    from lnnmpc.train.sharding import SeedPlacement

    values = dict(runfolder.read_config(run)["config"])
    values.pop("compile_cache", None)
    with tempfile.TemporaryDirectory() as scratch:  # a new, never created run path: validate writes nothing
        config = TrainConfig.from_dict(values, out=os.path.join(scratch, "run"))
        setup = validate(config, create=False)
    placement = SeedPlacement(setup.num_devices)
    state = placement.abstract(setup.state_shapes)
    keys = placement.abstract(jax.eval_shape(lambda: jax.random.split(jax.random.key(0), config.seeds)))
    lengths = {"train_chunk": setup.chunk, "seed_chunk": setup.seed_iterations,
               "update_burst": setup.burst_updates}
    texts = {name: placement.compile(getattr(setup.loop, name), length).lower(state).as_text()
             for name, length in lengths.items()}
    texts["evaluate"] = placement.compile(setup.loop.evaluate_logged).lower(state.agent, keys).as_text()
    return texts


def digest(text: str) -> str:
    """The first 16 hex digits of the sha256 of ``text`` (UTF-8)."""
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def scatter_counts(text: str) -> dict[str, int]:
    """``{"adding": n, "other": m}``: the scatters in StableHLO ``text`` (JAX's ``Lowered.as_text()``) whose update
    region adds (``stablehlo.add``) and whose ``unique_indices`` is false, and all other scatters."""
    counts = {"adding": 0, "other": 0}
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if '"stablehlo.scatter"' not in line:
            continue
        region = []
        for body in lines[i + 1:]:  # the update region, printed on the lines up to its closing "})"
            if body.lstrip().startswith("})"):
                break
            region.append(body)
        adding = any("stablehlo.add " in body for body in region) and "unique_indices = true" not in line
        counts["adding" if adding else "other"] += 1
    return counts


def scatter_table(counts: dict[str, dict[str, dict[str, int]]]) -> str:
    """Markdown: per run, each program's scatters as ``adding / other`` (:func:`scatter_counts`)."""
    lines = ["| run | " + " | ".join(f"{p} scatters (adding / other)" for p in PROGRAMS) + " |",
             "|---|" + "---:|" * len(PROGRAMS)]
    lines += [f"| {run} | " + " | ".join(f"{c[p]['adding']} / {c[p]['other']}" for p in PROGRAMS) + " |"
              for run, c in counts.items()]
    return "\n".join(lines)


def hash_table(hashes: dict[str, dict[str, str]]) -> str:
    """Markdown: one row per run and program; with several runs, one row per program saying whether all agree."""
    lines = ["| run | " + " | ".join(PROGRAMS) + " |", "|---|" + "---|" * len(PROGRAMS)]
    lines += [f"| {run} | " + " | ".join(h[p] for p in PROGRAMS) + " |" for run, h in hashes.items()]
    if len(hashes) > 1:
        same = ["same" if len({h[p] for h in hashes.values()}) == 1 else "differ" for p in PROGRAMS]
        lines.append("| all runs | " + " | ".join(same) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="program_hashes.py", description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", help="run folders (config.json)")
    p.add_argument("--dump", default=None, metavar="DIR", help="also write each program's text into DIR")
    p.add_argument("--scatters", action="store_true",
                   help="also count each program's scatters that add over indices not declared unique")
    args = p.parse_args(argv)
    from lnnmpc.train.config import ConfigError

    hashes, scatters = {}, {}
    try:
        for run in args.runs:
            texts = lowered_programs(run)
            label = os.path.basename(os.path.normpath(run))
            if label in hashes:
                label = run
            hashes[label] = {name: digest(text) for name, text in texts.items()}
            scatters[label] = {name: scatter_counts(text) for name, text in texts.items()}
            if args.dump:
                os.makedirs(args.dump, exist_ok=True)
                for name, text in texts.items():
                    with open(os.path.join(args.dump, f"{label.replace(os.sep, '_')}-{name}.txt"), "w") as f:
                        f.write(text)
    except ConfigError as e:
        sys.stderr.write(f"error: {e}\n")
        return 2
    sys.stdout.write(hash_table(hashes) + "\n")
    if args.scatters:
        sys.stdout.write("\n" + scatter_table(scatters) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
