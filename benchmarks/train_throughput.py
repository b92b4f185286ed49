"""TD-MPC2 training speed: act latency, update latency, env step, and end-to-end chunks versus seeds.

For each task and number of seeds (vmap), times with compile excluded (medians over ``--repeats``):
* ``act_ms``: one MPPI act step for every seed (vmap over seeds, one environment each);
* ``update_ms``: one update (batch 256, horizon 3) for every seed;
* ``chunk_env_steps_per_s``: a training chunk of ``--chunk`` iterations (act -> env step -> insert -> update),
  environment steps per second summed over seeds.
Writes JSON (device, versions, config, results), rewritten after each measurement.

    python benchmarks/train_throughput.py --tasks walker-run,cartpole-swingup --seeds 1,4,8
    python benchmarks/train_throughput.py --small --tasks cartpole-balance --seeds 1,2 --chunk 20   # CPU check
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import default_out, environment_info, time_call, write_json  # noqa: E402

from lnnmpc.train.cli import build, build_parser  # noqa: E402


def measure(task: str, seeds: int, args) -> dict:
    cli_args = ["--task", task, "--seeds", str(seeds), "--steps", "100000"] + (["--small"] if args.small else [])
    loop, _ = build(build_parser().parse_args(cli_args))
    ts = jax.jit(jax.vmap(loop.init))(jax.random.split(jax.random.key(0), seeds))
    seed_iters = args.fill
    seed_chunk = jax.jit(jax.vmap(loop.seed_chunk, in_axes=(0, None)), static_argnums=1)
    ts, _ = seed_chunk(ts, seed_iters)
    horizon, act_dim = loop.horizon, loop.env.action_size

    act = jax.jit(jax.vmap(lambda s, obs, k: loop.agent.act(s, obs, jnp.zeros((horizon, act_dim)), k, explore=True,
                                                            first_step=jnp.array(False))))
    obs = ts.env.obs[:, 0]
    act_t = time_call(act, ts.agent, obs, jax.random.split(jax.random.key(1), seeds), repeats=args.repeats)
    update = jax.jit(jax.vmap(loop._update))
    update_t = time_call(update, ts, jax.random.split(jax.random.key(2), seeds), repeats=args.repeats)
    train = jax.jit(jax.vmap(loop.train_chunk, in_axes=(0, None)), static_argnums=1)
    chunk_t = time_call(train, ts, args.chunk, repeats=max(1, args.repeats // 3))
    env_steps = seeds * args.chunk * loop.config.num_envs * loop.env.action_repeat
    return {
        "task": task, "seeds": seeds, "act_ms": 1e3 * act_t["median_s"], "update_ms": 1e3 * update_t["median_s"],
        "chunk_iterations": args.chunk, "chunk_s": chunk_t["median_s"],
        "chunk_env_steps_per_s": env_steps / chunk_t["median_s"],
        "ms_per_iteration": 1e3 * chunk_t["median_s"] / args.chunk, "compile_chunk_s": chunk_t["first_call_s"],
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", default="walker-run,cartpole-swingup")
    parser.add_argument("--seeds", default="1,4,8")
    parser.add_argument("--chunk", type=int, default=200, help="iterations per timed training chunk")
    parser.add_argument("--fill", type=int, default=600, help="random iterations to fill the replay first")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--small", action="store_true", help="tiny networks and planner (CPU check)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    out = args.out or default_out("train_throughput")
    payload = {"benchmark": "train_throughput", "env": environment_info(), "args": vars(args), "results": []}
    for task in args.tasks.split(","):
        for seeds in (int(s) for s in args.seeds.split(",")):
            record = measure(task, seeds, args)
            payload["results"].append(record)
            write_json(out, payload)
            print(f"{task:18s} seeds={seeds:2d}  act {record['act_ms']:8.2f} ms  update {record['update_ms']:8.2f} ms"
                  f"  chunk {record['ms_per_iteration']:8.2f} ms/iteration"
                  f"  {record['chunk_env_steps_per_s']:10.0f} env steps/s", flush=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
