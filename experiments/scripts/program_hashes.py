"""The programs a run trains with, lowered here from its config.json, named by the sha256 of their StableHLO text.

    PYTHONPATH=<checkout>/src python experiments/scripts/program_hashes.py RUN [RUN ...] [--dump DIR]

For each run folder: the training chunk, the seed phase, the update burst and the evaluation, lowered (traced, not
compiled) on this machine's JAX device for the run's recorded settings, each with the first 16 hex digits of the
sha256 of its text. With several runs a last table says, program by program, whether all runs' texts are equal.
Lowering with another checkout's ``src`` on ``PYTHONPATH`` tells whether two commits build the same programs for
one configuration: RESULTS.md [91] found the acrobot recipe's four programs byte-identical at ``0c4e564`` and
``3560bc0``, so its two launches that parted on the GPU had run the same programs. ``--dump DIR`` also writes each
text to ``DIR/<run name>-<program>.txt`` for a diff.
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
    args = p.parse_args(argv)
    from lnnmpc.train.config import ConfigError

    hashes = {}
    try:
        for run in args.runs:
            texts = lowered_programs(run)
            label = os.path.basename(os.path.normpath(run))
            if label in hashes:
                label = run
            hashes[label] = {name: digest(text) for name, text in texts.items()}
            if args.dump:
                os.makedirs(args.dump, exist_ok=True)
                for name, text in texts.items():
                    with open(os.path.join(args.dump, f"{label.replace(os.sep, '_')}-{name}.txt"), "w") as f:
                        f.write(text)
    except ConfigError as e:
        sys.stderr.write(f"error: {e}\n")
        return 2
    sys.stdout.write(hash_table(hashes) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
