"""Training speed of one agent (``--agent``: tdmpc2 or a liquid variant): act, update and env step latency,
and end-to-end chunks versus seeds.

For each task and number of seeds (vmap), times with compile excluded (medians over ``--repeats``):
* ``act_ms``: one MPPI act step for every seed (vmap over seeds, one environment each);
* ``update_ms``: one update (batch 256; the agent's training window) for every seed; ``update_gflop`` its
  arithmetic by XLA's cost analysis and ``update_tflop_per_s`` the rate achieved; ``update_compile_s`` the
  seconds to lower and compile it (``--update-only`` stops here);
* ``chunk_env_steps_per_s``: a training chunk of ``--chunk`` iterations (act -> env step -> insert -> update),
  environment steps per second summed over seeds (``--chunk-only`` times nothing else: one compilation);
* with ``--in-scan N``: ``update_in_scan_ms`` (and, unless ``--update-only``, ``act_in_scan_ms`` and
  ``env_in_scan_ms``): the cost of one call when N of them run inside one ``lax.scan``, as the training chunk
  runs them (the update: ``TrainingLoop.update_burst``). A standalone call also pays for its dispatch and
  per-call set-up: on an H100 the standalone act, env step and update times of TD-MPC2 summed to 1.4-1.9x the
  chunk's time per iteration (``benchmarks/results/README.md``), so ``parts_in_scan_ms`` is the breakdown of an
  iteration to compare with it.
Writes JSON (device, versions, config, results), rewritten after each measurement.

    python benchmarks/train_throughput.py --tasks walker-run,cartpole-swingup --seeds 1,4,8
    python benchmarks/train_throughput.py --small --tasks cartpole-balance --seeds 1,2 --chunk 20   # CPU check
    python benchmarks/train_throughput.py --tasks walker-run --seeds 4 --skip-chunk --matmul-precision bfloat16
    python benchmarks/train_throughput.py --tasks walker-run --agent cfc-zp-det --seeds 3 --envs 16 --in-scan 16
    python benchmarks/train_throughput.py --tasks walker-run --agent cfc-zp-det --seeds 1 --envs 16 --chunk-only
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
import time

import jax
import jax.numpy as jnp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import compiled_gflop, default_out, environment_info, time_call, tree_digest, write_json  # noqa: E402

from lnnmpc import envs as envs_lib  # noqa: E402
from lnnmpc.agents.registry import make_agent  # noqa: E402
from lnnmpc.train.config import parse_overrides  # noqa: E402
from lnnmpc.train.loop import LoopConfig, TrainingLoop, windows_after_seed_phase  # noqa: E402

REPLAY_CAPACITY = 51_000


def build_loop(task: str, agent: str, envs: int, small: bool, overrides: dict | None = None,
               batch_size: int = 256, fill: int | None = None) -> TrainingLoop:
    """The trainer's loop with default settings (replay sized for 100K environment steps, ``batch_size``
    sequences per update), agent ``overrides`` as ``--set`` gives them. ``fill``: the random iterations the
    replay gets before the measurement; the update's guard against an empty replay
    (``LoopConfig.guard_empty_replay``) is then on or off as the trainer sets it after a seed phase that long
    (``None``: on, the loop's default)."""
    env = envs_lib.make(task)
    agent = make_agent(agent, env.observation_size, env.action_size, small=small, overrides=overrides or {})
    guard = fill is None or not windows_after_seed_phase(fill, env.episode_length, agent.sequence_length,
                                                         REPLAY_CAPACITY)
    return TrainingLoop(agent, env, env, LoopConfig(num_envs=envs, batch_size=batch_size,
                                                    replay_capacity=REPLAY_CAPACITY, guard_empty_replay=guard))


def filled_state(loop: TrainingLoop, seeds: int, fill: int):
    """The loop's training state for ``seeds`` seeds (vmap) after ``fill`` iterations of random actions."""
    ts = jax.jit(jax.vmap(loop.init))(jax.random.split(jax.random.key(0), seeds))
    seed_chunk = jax.jit(jax.vmap(loop.seed_chunk, in_axes=(0, None)), static_argnums=1)
    return seed_chunk(ts, fill)[0]


def act_over_seeds_and_envs(agent):
    """The act step with exploration, vmapped over seeds x environments (not jitted):
    (agent state, carry, obs, dt, keys) -> (action, next carry)."""
    one = lambda s, carry, obs, dt, k: agent.act(s, carry, obs, dt, k, explore=True, first_step=jnp.array(False))
    return jax.vmap(jax.vmap(one, in_axes=(None, 0, 0, 0, 0)))


def env_step_over_seeds_and_envs(loop: TrainingLoop):
    """The environment step as the training chunk takes it (``Env.step_or_reset``: one physics program steps the
    running environments and restarts the finished ones), vmapped over seeds x environments (not jitted):
    (env states, actions, keys) -> states; ``keys`` (seeds, envs) draw the restarts' initial states."""
    def one(env, action, key):
        return loop.env.step_or_reset(env, action, env.done, key)
    return jax.vmap(jax.vmap(one))


def update_burst_program(loop: TrainingLoop):
    """``TrainingLoop.update_burst`` vmapped over seeds and jitted: (ts, number of updates, static) -> (ts,
    metrics); the updates run in one ``lax.scan``, as the training chunk runs them."""
    return jax.jit(jax.vmap(loop.update_burst, in_axes=(0, None)), static_argnums=1)


def act_call(agent, ts):
    """The jitted act step with exploration over seeds x environments, and its arguments from ``ts``."""
    keys = jax.random.split(jax.random.key(1), ts.episode_return.shape)  # (seeds, envs)
    return jax.jit(act_over_seeds_and_envs(agent)), (ts.agent, ts.carry, ts.env.obs, ts.env.dt, keys)


def update_call(loop: TrainingLoop, ts):
    """One update for every seed, compiled (for timing and XLA's cost analysis), and its arguments."""
    keys = jax.random.split(jax.random.key(2), ts.episode_return.shape[0])
    return jax.jit(jax.vmap(loop._update)).lower(ts, keys).compile(), (ts, keys)


def in_scan_calls(loop: TrainingLoop, ts, n: int) -> dict:
    """Programs that run ``n`` act steps, environment steps or updates (every seed) inside one ``lax.scan``, as
    the training chunk runs them, with their arguments: {"act" | "env" | "update": (jitted fn, args)}. The act
    steps chain the planner's carry from the same observations; the environment steps apply zero actions."""
    act, step = act_over_seeds_and_envs(loop.agent), env_step_over_seeds_and_envs(loop)

    def acts(agent, carry, obs, dt, keys):  # keys (n, seeds, envs)
        def body(carry, k):
            action, carry = act(agent, carry, obs, dt, k)
            return carry, action
        return jax.lax.scan(body, carry, keys)

    def env_steps(env, actions, env_keys):  # env_keys (n, seeds, envs)
        return jax.lax.scan(lambda env, k: (step(env, actions, k), None), env, env_keys)[0]

    keys = jax.random.split(jax.random.key(3), (n, *ts.episode_return.shape))
    env_keys = jax.random.split(jax.random.key(4), (n, *ts.episode_return.shape))
    actions = jnp.zeros((*ts.episode_return.shape, loop.env.action_size))
    burst = update_burst_program(loop)
    return {"act": (jax.jit(acts), (ts.agent, ts.carry, ts.env.obs, ts.env.dt, keys)),
            "env": (jax.jit(env_steps), (ts.env, actions, env_keys)),
            "update": (lambda ts: burst(ts, n), (ts,))}


def time_in_scan(loop: TrainingLoop, ts, n: int, parts: tuple[str, ...], repeats: int) -> dict:
    """``{part}_in_scan_ms``: milliseconds per call of each of ``parts`` run ``n`` at a time in one scan."""
    calls = in_scan_calls(loop, ts, n)
    return {f"{part}_in_scan_ms": 1e3 * time_call(calls[part][0], *calls[part][1], repeats=repeats)["median_s"] / n
            for part in parts}


def measure(task: str, seeds: int, envs: int, args) -> dict:
    loop = build_loop(task, args.agent, envs, args.small, parse_overrides(args.overrides),
                      fill=None if args.keep_replay_guard else args.fill)
    ts = filled_state(loop, seeds, args.fill)
    act_dim = loop.env.action_size
    record = {"task": task, "agent": args.agent, "seeds": seeds, "envs": envs,
              "guard_empty_replay": loop.config.guard_empty_replay}
    if args.chunk_only:  # one compilation (the chunk's) instead of four
        record.update(time_chunk(loop, ts, seeds, envs, args.chunk, args.repeats))
        return record
    update_start = time.perf_counter()
    update, update_args = update_call(loop, ts)  # timed and cost-analysed
    record["update_compile_s"] = time.perf_counter() - update_start  # lowering + XLA compilation
    record["update_ms"] = 1e3 * time_call(update, *update_args, repeats=args.repeats)["median_s"]
    # XLA's count of the update's arithmetic, and the rate it ran at: far below the device's peak means the
    # update is latency-bound (many small kernels), not compute-bound.
    record["update_gflop"] = compiled_gflop(update)
    if record["update_gflop"] is not None:
        record["update_tflop_per_s"] = record["update_gflop"] / record["update_ms"]
    if args.in_scan:
        parts = ("update",) if args.update_only else ("act", "env", "update")
        record["in_scan"] = args.in_scan
        record.update(time_in_scan(loop, ts, args.in_scan, parts, max(1, args.repeats // 3)))
        if not args.update_only:
            record["parts_in_scan_ms"] = {"act": record["act_in_scan_ms"], "env": record["env_in_scan_ms"],
                                          "updates": envs * record["update_in_scan_ms"]}
    if args.update_only:
        return record
    act, act_args = act_call(loop.agent, ts)
    act_t = time_call(act, *act_args, repeats=args.repeats)
    record["act_ms"] = 1e3 * act_t["median_s"]
    if args.compare_unroll:
        rolled = type(loop.agent)(dataclasses.replace(
            loop.agent.config, planner=dataclasses.replace(loop.agent.config.planner, unroll=False)))
        act_rolled = act_call(rolled, ts)[0]
        record["act_rolled_ms"] = 1e3 * time_call(act_rolled, *act_args, repeats=args.repeats)["median_s"]
    env_step = jax.jit(env_step_over_seeds_and_envs(loop))
    actions = jnp.zeros((seeds, envs, act_dim))
    env_keys = jax.random.split(jax.random.key(4), (seeds, envs))
    record["env_ms"] = 1e3 * time_call(env_step, ts.env, actions, env_keys, repeats=args.repeats)["median_s"]
    # Where an iteration's time goes if the parts ran back to back (act, env step, envs x update).
    record["parts_ms"] = {"act": record["act_ms"], "env": record["env_ms"], "updates": envs * record["update_ms"]}
    if not args.skip_chunk:
        record.update(time_chunk(loop, ts, seeds, envs, args.chunk, max(1, args.repeats // 3)))
    return record


def time_chunk(loop: TrainingLoop, ts, seeds: int, envs: int, iterations: int, repeats: int) -> dict:
    """The training chunk of ``iterations`` (act -> env step -> insert -> update) over every seed: its median
    seconds, environment steps per second summed over seeds, ms per iteration, first call (compilation), and
    ``chunk_digest``, :func:`common.tree_digest` of the last timed call's output state (the same input every
    call). On a GPU two processes agree only under ``XLA_FLAGS=--xla_gpu_deterministic_ops=true``: without it the
    same program's sums vary in round-off (run 34), so compare digests of runs made under that flag."""
    train = jax.jit(jax.vmap(loop.train_chunk, in_axes=(0, None)), static_argnums=1)
    chunk_t = time_call(train, ts, iterations, repeats=repeats, keep_output=True)
    env_steps = seeds * iterations * envs * loop.env.action_repeat
    return {"chunk_iterations": iterations, "chunk_s": chunk_t["median_s"],
            "chunk_env_steps_per_s": env_steps / chunk_t["median_s"],
            "ms_per_iteration": 1e3 * chunk_t["median_s"] / iterations, "compile_chunk_s": chunk_t["first_call_s"],
            "chunk_digest": tree_digest(chunk_t["output"])}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", default="walker-run,cartpole-swingup")
    parser.add_argument("--agent", default="tdmpc2")
    parser.add_argument("--seeds", default="1,4,8")
    parser.add_argument("--envs", default="1", help="environments per seed (comma list)")
    parser.add_argument("--compare-unroll", action="store_true", help="also time the act step with rolled scans")
    parser.add_argument("--chunk", type=int, default=200, help="iterations per timed training chunk")
    parser.add_argument("--fill", type=int, default=600, help="random iterations to fill the replay first")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--skip-chunk", action="store_true",
                        help="time act, env step and update only (no end-to-end chunk: saves its compilation)")
    parser.add_argument("--update-only", action="store_true",
                        help="time the update alone (no act step, env step or chunk)")
    parser.add_argument("--chunk-only", action="store_true",
                        help="time the training chunk alone, --repeats times (no standalone act, env step or update)")
    parser.add_argument("--in-scan", type=int, default=0, metavar="N",
                        help="also time act, env step and update N at a time inside one lax.scan (0: off)")
    parser.add_argument("--small", action="store_true", help="tiny networks and planner (CPU check)")
    parser.add_argument("--keep-replay-guard", action="store_true",
                        help="keep the update's empty-replay guard the trainer drops after a long enough seed phase")
    parser.add_argument("--matmul-precision", choices=("default", "tensorfloat32", "bfloat16", "highest"),
                        default="default", help="jax_default_matmul_precision for every program timed")
    parser.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE",
                        help="agent hyperparameter override, repeatable (e.g. --set flat_optimizer=true)")
    parser.add_argument("--out", default=None, help="JSON path; {device} in it becomes h100, h200, cpu, ...")
    args = parser.parse_args(argv)
    if args.in_scan < 0:
        parser.error(f"--in-scan must be >= 0 (0: off), got {args.in_scan}")
    if args.chunk_only and (args.update_only or args.skip_chunk or args.in_scan):
        parser.error("--chunk-only times the chunk alone: drop --update-only, --skip-chunk and --in-scan")
    if args.chunk < 1:
        parser.error(f"--chunk must be >= 1 iteration, got {args.chunk}")
    if args.matmul_precision != "default":
        jax.config.update("jax_default_matmul_precision", args.matmul_precision)
    out = args.out or default_out("train_throughput")
    payload = {"benchmark": "train_throughput", "env": environment_info(), "args": vars(args), "results": []}
    for task in args.tasks.split(","):
        for seeds, envs in itertools.product(map(int, args.seeds.split(",")), map(int, args.envs.split(","))):
            record = measure(task, seeds, envs, args)
            payload["results"].append(record)
            out = write_json(out, payload)
            if args.chunk_only:
                print(f"{task:18s} {args.agent:12s} seeds={seeds:2d} envs={envs:2d}  chunk "
                      f"{record['ms_per_iteration']:8.2f} ms/iteration  {record['chunk_env_steps_per_s']:10.0f} env "
                      f"steps/s (compiled in {record['compile_chunk_s']:.1f} s)", flush=True)
                continue
            if args.update_only:
                in_scan = (f", {record['update_in_scan_ms']:.2f} ms in a scan of {args.in_scan}"
                           if args.in_scan else "")
                print(f"{task:18s} {args.agent:12s} seeds={seeds:2d}  update {record['update_ms']:8.2f} ms"
                      f" (compiled in {record['update_compile_s']:.1f} s){in_scan}", flush=True)
                continue
            chunk = ("" if args.skip_chunk else f"  chunk {record['ms_per_iteration']:8.2f} ms/iteration"
                     f"  {record['chunk_env_steps_per_s']:10.0f} env steps/s")
            print(f"{task:18s} {args.agent:12s} seeds={seeds:2d} envs={envs:2d}  env {record['env_ms']:6.2f} ms"
                  f"  act {record['act_ms']:8.2f} ms  update {record['update_ms']:8.2f} ms"
                  f" ({record.get('update_tflop_per_s') or 0:.1f} TFLOP/s){chunk}", flush=True)
            if args.in_scan:
                print(f"{'':18s} in a scan of {args.in_scan}: env {record['env_in_scan_ms']:6.2f} ms  act "
                      f"{record['act_in_scan_ms']:8.2f} ms  update {record['update_in_scan_ms']:8.2f} ms", flush=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
