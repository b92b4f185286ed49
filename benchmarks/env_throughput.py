"""Environment throughput: ms per agent step and agent steps/s versus batch size, per domain and profile.

One measurement = a jitted ``lax.scan`` of ``--steps`` agent steps (action repeat 2, uniform random actions) over
a ``vmap`` batch of environments; compile excluded, median over ``--repeats``. Results go to JSON, rewritten after
every measurement so that an interrupted run keeps what it measured.

    python benchmarks/env_throughput.py                          # fast profile, batches 1,16,256,4096
    python benchmarks/env_throughput.py --profiles exact --batches 1,256 --steps 10
    python benchmarks/env_throughput.py --walker-sweep           # candidate fast settings for walker
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import jax

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import default_out, environment_info, time_call, write_json  # noqa: E402

from lnnmpc import envs  # noqa: E402

DOMAIN_TASKS = {"cartpole": "cartpole-swingup", "acrobot": "acrobot-swingup", "walker": "walker-run"}
WALKER_SWEEP = {
    "fast": envs.PhysicsOptions(iterations=1, ls_iterations=4),
    "fast+noeulerdamp": envs.PhysicsOptions(iterations=1, ls_iterations=4, disable_eulerdamp=True),
    "it1-ls1": envs.PhysicsOptions(iterations=1, ls_iterations=1),
    "fast+contacts4": envs.PhysicsOptions(iterations=1, ls_iterations=4, max_contact_points=4),
    "it2-ls4": envs.PhysicsOptions(iterations=2, ls_iterations=4),
    "it3-ls6": envs.PhysicsOptions(iterations=3, ls_iterations=6),
    "it4-ls8": envs.PhysicsOptions(iterations=4, ls_iterations=8),
    "it4-ls8+noeulerdamp": envs.PhysicsOptions(iterations=4, ls_iterations=8, disable_eulerdamp=True),
    "it4-ls4": envs.PhysicsOptions(iterations=4, ls_iterations=4),
    "it3-ls4": envs.PhysicsOptions(iterations=3, ls_iterations=4),
    "cg-it8-ls8": envs.PhysicsOptions(solver="cg", iterations=8, ls_iterations=8),
    "unrolled-it4-ls4": envs.PhysicsOptions(iterations=4, ls_iterations=4, unrolled_solver=True),
    "unrolled-it3-ls4": envs.PhysicsOptions(iterations=3, ls_iterations=4, unrolled_solver=True),
    "unrolled-it4-ls2": envs.PhysicsOptions(iterations=4, ls_iterations=2, unrolled_solver=True),
}


def rollout_fn(env: envs.Env):
    """jit((states (B,), actions (B, T, nu)) -> final states): T agent steps per environment, no resets."""

    def one(state, actions):
        state, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), state, actions)
        return state

    return jax.jit(jax.vmap(one))


def measure(task: str, physics, batch: int, steps: int, repeats: int) -> dict:
    env = envs.make(task, physics=physics, action_repeat=2)
    keys = jax.random.split(jax.random.key(0), batch)
    states = jax.block_until_ready(jax.jit(jax.vmap(env.reset))(keys))
    actions = jax.random.uniform(jax.random.key(1), (batch, steps, env.action_size), minval=-1.0, maxval=1.0)
    timing = time_call(rollout_fn(env), states, actions, repeats=repeats)
    per_step = timing["median_s"] / steps
    return {
        "task": task, "domain": env.spec.domain, "batch": batch, "steps": steps, "action_repeat": 2,
        "physics_options": dataclasses.asdict(env.physics_options),
        "rollout_median_s": timing["median_s"], "rollout_times_s": timing["times_s"],
        "compile_s": timing["first_call_s"], "ms_per_agent_step": 1e3 * per_step,
        "agent_steps_per_s": batch / per_step,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--domains", default="cartpole,acrobot,walker")
    parser.add_argument("--profiles", default="fast")
    parser.add_argument("--batches", default="1,16,256,4096")
    parser.add_argument("--steps", type=int, default=50, help="agent steps per timed rollout")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--walker-sweep", action="store_true", help="time candidate walker settings instead")
    parser.add_argument("--sweep", default=",".join(WALKER_SWEEP), help="which candidates --walker-sweep times")
    parser.add_argument("--out", default=None, help="JSON path; {device} in it becomes h100, h200, cpu, ...")
    args = parser.parse_args(argv)
    batches = [int(b) for b in args.batches.split(",")]
    out = args.out or default_out("env_throughput" + ("-walker-sweep" if args.walker_sweep else ""))
    payload = {"benchmark": "env_throughput", "env": environment_info(), "args": vars(args), "results": []}
    if args.walker_sweep:
        jobs = [("walker-run", name, WALKER_SWEEP[name], b) for name in args.sweep.split(",") for b in batches]
    else:
        jobs = [
            (DOMAIN_TASKS[d], p, p, b) for p in args.profiles.split(",") for d in args.domains.split(",")
            for b in batches
        ]
    for i, (task, label, physics, batch) in enumerate(jobs):
        start = time.perf_counter()
        record = measure(task, physics, batch, args.steps, args.repeats)
        record["profile"] = label
        payload["results"].append(record)
        out = write_json(out, payload)
        print(
            f"[{i + 1}/{len(jobs)}] {task:18s} {label:18s} B={batch:5d}  {record['ms_per_agent_step']:8.3f} ms/step"
            f"  {record['agent_steps_per_s']:12.0f} steps/s  (compile {record['compile_s']:.1f}s, "
            f"total {time.perf_counter() - start:.1f}s)",
            flush=True,
        )
    print(f"wrote {out}")
    return payload


if __name__ == "__main__":
    main()
