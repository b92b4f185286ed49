"""How many XLA ops the TD-MPC2 update compiles to, with the optimisers as they are and with each optimiser's
Adam over one flat vector (``optax.flatten``), on this machine's backend (CPU here: a proxy for the GPU's kernel
count, since the update is latency-bound; see benchmarks/results/README.md).

    python benchmarks/update_kernels.py [--task walker-run] [--out results/<file>.json]

The flattened variant ignores the encoder's learning-rate scale and the frozen groups (it only counts ops); it is
a measurement for deciding whether a flat optimiser is worth building, not a training setting.
"""

import argparse
import re
import sys

import jax
import jax.numpy as jnp
import optax

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
    agent = make_agent(args.agent, env.observation_size, env.action_size)
    counts = {"as_built": update_op_counts(agent, env)}
    clip = optax.clip_by_global_norm(agent.config.grad_clip_norm)
    agent.model_tx = optax.flatten(optax.chain(clip, optax.adam(agent.config.lr)))
    agent.policy_tx = optax.flatten(optax.chain(clip, optax.adam(agent.config.lr, eps=1e-5)))
    counts["flat_adam"] = update_op_counts(agent, env)
    for name, value in counts.items():
        print(jax.default_backend(), args.agent, args.task, name, value)
    if args.out:
        write_json(args.out, {"environment": environment_info(), "config": vars(args), "update_ops": counts})


if __name__ == "__main__":
    main()
