"""How many XLA ops an agent's update compiles to, on this machine's backend (on the CPU a proxy for the GPU's
kernel count, since the update is latency-bound; see benchmarks/results/README.md). Two modes:

* default: the agent's bare update (B = 256) with Adam per parameter leaf and with ``flat_optimizer`` (each
  optimiser's Adam over one flat vector, ``optax.flatten``): fusions and instructions of the entry computation;
* ``--loop-seeds N``: the training loop's update as the trainer compiles it (``vmap`` over N seeds, replay
  sample included, the agent's task defaults plus ``--set`` overrides): every launched op of the entry
  computation and of the loop bodies (fused computations and reducers excluded), by kind and by the update's
  named scope (``profile_update.SCOPES``).

    python benchmarks/update_kernels.py [--task walker-run] [--out results/<file>.json]
    python benchmarks/update_kernels.py --agent cfc-zp-det --loop-seeds 3 [--batch-size 128] --out results/<file>.json
"""

import argparse
import collections
import re
import sys

import jax
import jax.numpy as jnp

from lnnmpc import envs
from lnnmpc.agents.registry import make_agent

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import compiled_gflop, environment_info, write_json  # noqa: E402
from profile_update import scope_label  # noqa: E402
from train_throughput import build_loop, update_call  # noqa: E402

from lnnmpc.agents.registry import task_default_overrides  # noqa: E402
from lnnmpc.train.config import parse_overrides  # noqa: E402

# Instructions that launch nothing themselves (bookkeeping, or control flow whose bodies are counted instead).
NOT_LAUNCHED = {"parameter", "get-tuple-element", "tuple", "bitcast", "constant", "while", "call", "conditional",
                "after-all", "opt-barrier"}


def update_op_counts(agent, env) -> dict:
    """Fusions and all instructions in the entry computation of the compiled update (B = 256), and param leaves."""
    state = agent.init(jax.random.key(0))
    n = agent.sequence_length
    record = agent.replay_record(jnp.zeros((env.observation_size,)), jnp.zeros((env.action_size,)), jnp.zeros(()),
                                 jnp.ones(()), agent.initial_carry())
    batch = jax.tree_util.tree_map(lambda x: jnp.zeros((n, 256) + jnp.shape(x), jnp.asarray(x).dtype), record)
    text = jax.jit(agent.update).lower(state, batch, jax.random.key(1)).compile().as_text()
    entry = text[text.index("ENTRY"):]
    return {"fusions": len(re.findall(r"= \S+ fusion\(", entry)),
            "instructions": len(re.findall(r"^\s+\S+ = ", entry, re.M)),
            "param_leaves": len(jax.tree_util.tree_leaves(state.params))}


def launched_ops(hlo_text: str) -> dict:
    """The ops of a compiled HLO module that run as their own kernels: those of the entry computation and of
    the computations it runs as loop bodies and conditions, not those inside fusions or reducers; counted in
    all, by kind and by :func:`profile_update.scope_label` of their ``op_name``."""
    called = set(re.findall(r"(?:calls|to_apply|comparator)=%?([\w.\-]+)", hlo_text))
    kinds, scopes = collections.Counter(), collections.Counter()
    for entry, name, body in re.findall(r"^(ENTRY )?%?([\w.\-]+) [^\n]*\{\n(.*?)\n\}", hlo_text, re.M | re.S):
        if name in called and not entry:
            continue
        for match in re.finditer(r"^\s*(?:ROOT )?%?[\w.\-]+ = (?:\([^=]*\)|\S+) ([\w\-]+)\(([^\n]*)", body, re.M):
            if match.group(1) in NOT_LAUNCHED:
                continue
            op_name = re.search(r'op_name="([^"]+)"', match.group(2))
            kinds[match.group(1)] += 1
            scopes[scope_label(op_name.group(1) if op_name else None)] += 1
    return {"ops": sum(kinds.values()), "by_kind": dict(kinds.most_common()), "by_scope": dict(scopes.most_common())}


def loop_update_ops(task: str, agent: str, seeds: int, overrides: dict, batch_size: int = 256) -> dict:
    """:func:`launched_ops` of the trainer's update of ``seeds`` seeds (vmap, ``batch_size`` sequences each),
    with XLA's GFLOP count."""
    loop = build_loop(task, agent, 1, False, task_default_overrides(agent, task, overrides), batch_size)
    shapes = jax.eval_shape(jax.vmap(loop.init), jax.random.split(jax.random.key(0), seeds))  # shapes suffice
    compiled = update_call(loop, shapes)[0]
    return {**launched_ops(compiled.as_text()), "gflop": compiled_gflop(compiled)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="walker-run")
    parser.add_argument("--agent", default="tdmpc2")
    parser.add_argument("--loop-seeds", type=int, default=None,
                        help="count the trainer's update of this many seeds instead (see the module docstring)")
    parser.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE",
                        help="agent hyperparameter override for --loop-seeds, repeatable")
    parser.add_argument("--batch-size", type=int, default=256, help="sequences per update for --loop-seeds")
    parser.add_argument("--out", default=None,
                        help="JSON file for the counts, with device and versions ({device} becomes h100, cpu, ...)")
    args = parser.parse_args()
    if args.loop_seeds is not None:
        if args.loop_seeds < 1:
            parser.error(f"--loop-seeds must be >= 1, got {args.loop_seeds}")
        if args.batch_size < 1:
            parser.error(f"--batch-size must be >= 1, got {args.batch_size}")
        counts = {"loop_update": loop_update_ops(args.task, args.agent, args.loop_seeds,
                                                 parse_overrides(args.overrides), args.batch_size)}
    else:
        env = envs.make(args.task)
        counts = {}
        for flat in (False, True):
            agent = make_agent(args.agent, env.observation_size, env.action_size, overrides={"flat_optimizer": flat})
            counts["flat_optimizer" if flat else "per_leaf"] = update_op_counts(agent, env)
    for name, value in counts.items():
        print(jax.default_backend(), args.agent, args.task, name, value)
    if args.out:
        out = write_json(args.out, {"environment": environment_info(), "config": vars(args), "update_ops": counts})
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
