"""How many XLA ops an agent's update compiles to, with Adam per parameter leaf and with ``flat_optimizer`` (each
optimiser's Adam over one flat vector, ``optax.flatten``), on this machine's backend (on the CPU a proxy for the
GPU's kernel count, since the update is latency-bound; see benchmarks/results/README.md).

    python benchmarks/update_kernels.py [--task walker-run] [--out results/<file>.json]
"""

import argparse
import re
import sys

import jax
import jax.numpy as jnp

from lnnmpc import envs
from lnnmpc.agents.registry import make_agent

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import environment_info, write_json  # noqa: E402


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="walker-run")
    parser.add_argument("--agent", default="tdmpc2")
    parser.add_argument("--out", default=None, help="JSON file for the counts (with device and versions)")
    args = parser.parse_args()
    env = envs.make(args.task)
    counts = {}
    for flat in (False, True):
        agent = make_agent(args.agent, env.observation_size, env.action_size, overrides={"flat_optimizer": flat})
        counts["flat_optimizer" if flat else "per_leaf"] = update_op_counts(agent, env)
    for name, value in counts.items():
        print(jax.default_backend(), args.agent, args.task, name, value)
    if args.out:
        write_json(args.out, {"environment": environment_info(), "config": vars(args), "update_ops": counts})


if __name__ == "__main__":
    main()
