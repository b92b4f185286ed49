"""``python -m lnnmpc.analysis.elite_outcomes``: do MPPI's elites' predicted values rank what they pay on MJX?

    python -m lnnmpc.analysis.elite_outcomes RUN [--checkpoint STEP] [--episodes 4] [--seed 0] [--elites 16]
        [--follow 60] [--max-reward 0.1] [--out CSV]

Where a trained acrobot hangs, MPPI's final elites are valued nearly alike (RESULTS.md [116]): is that the critic (a
flat value where the outcomes differ) or the task (outcomes that differ little over the plan's horizon)? This
command plays the run's policy (trained seed 0) for the deterministic episodes ``cli eval --seed`` plays, takes in
each episode the first agent step t* whose reward is under ``--max-reward`` (the tip far from the target; from most
starts, the episode's first step), and there asks MPPI for its plan as the agent would (the same key). Of its final
elites (best first) it keeps ``--elites`` ranks spread evenly from the best to the last, and plays each on MJX from
the same state: the elite's H planned actions (the agent's encoder reading each step as it would), then ``--follow``
agent steps of the agent's own deterministic acting. MPPI's warm start there is still the plan of t* (``observe``
leaves it; MPPI restarts its std at ``max_std`` every call).

For each episode it prints the elites' predicted values G (their spread), the discounted return they paid over
the H + ``--follow`` steps (the planner's gamma per agent step; its spread) and the rank correlation between the
two. The paid return is truncated, so only its differences compare with G's. ``--out`` writes one row per elite:
episode, t, rank, predicted, paid (discounted), paid_sum (undiscounted). A live line on stderr counts the agent
steps played.
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.train.config import ConfigError
from lnnmpc.train.step_report import report_step, reporting

COLUMNS = ("episode", "t", "rank", "predicted", "paid", "paid_sum")


class _Tracing:
    """``agent`` acting as usual, its carry extended by the carry it acted from: ``(next carry, carry before)``."""

    def __init__(self, agent: Any):
        self.agent = agent

    def initial_carry(self):
        return self.agent.initial_carry(), self.agent.initial_carry()

    def act(self, state, carry, obs, dt, key, *, explore: bool, first_step):
        action, nxt = self.agent.act(state, carry[0], obs, dt, key, explore=explore, first_step=first_step)
        return action, (nxt, carry[0])


@functools.lru_cache(maxsize=4)
def _trace_program(pair: Any, episodes: int):
    """Deterministic episodes of ``pair`` (a :class:`lnnmpc.train.evaluate.SameProgram`) as
    :func:`lnnmpc.train.loop.play_episodes` plays them, recording at every agent step the environments' state and
    the acting carry before the step, and the step's reward (time-major)."""
    from lnnmpc.train.loop import play_episodes

    def record(state, carry, action, nxt):
        return state, carry[1], nxt.reward

    return jax.jit(lambda s, k: play_episodes(_Tracing(pair.agent), s, pair.env, k, episodes, record=record)[1])


def elite_rollouts(agent: Any, agent_state: Any, env: Any, env_state: Any, carry: Any, key: jax.Array,
                   ranks: jax.Array, follow: int) -> tuple[jax.Array, jax.Array]:
    """From one environment state and the acting carry before it: MPPI's plan as the agent makes it with ``key``
    (no exploration); for each elite rank in ``ranks`` (n,), its predicted value and the rewards (n, H + follow) of
    playing its H actions and then ``follow`` agent steps of the agent's own deterministic acting. Returns
    (predicted (n,), rewards (n, H + follow))."""
    first = env_state.t == 0
    _, _, info = agent.act_planned(agent_state, carry, env_state.obs, env_state.dt, key, explore=False,
                                   first_step=first)
    predicted = info["elite_values"][ranks]
    actions = jnp.swapaxes(info["elite_actions"][:, ranks], 0, 1)  # (n, H, A)

    def forced(loop, action):
        c, s = loop
        c = agent.observe(agent_state, c, s.obs, s.dt, action, first_step=first & (s.t == env_state.t))
        nxt = env.step(s, action)
        return (c, nxt), nxt.reward

    def acting(loop, j):
        c, s = loop
        action, c = agent.act(agent_state, c, s.obs, s.dt, jax.random.fold_in(key, j + 1), explore=False,
                              first_step=jnp.asarray(False))
        nxt = env.step(s, action)
        jax.debug.callback(report_step, j)
        return (c, nxt), nxt.reward

    def one(elite):
        loop, planned = jax.lax.scan(forced, (carry, env_state), elite)
        _, followed = jax.lax.scan(acting, loop, jnp.arange(follow))
        return jnp.concatenate([planned, followed])

    return predicted, jax.vmap(one)(actions)


@functools.lru_cache(maxsize=4)
def _rollout_program(pair: Any, follow: int):
    """:func:`elite_rollouts` of ``pair`` (a :class:`lnnmpc.train.evaluate.SameProgram`) over a batch of starts
    (states, carries and keys with a leading axis)."""
    return jax.jit(jax.vmap(lambda a, s, c, k, r: elite_rollouts(pair.agent, a, pair.env, s, c, k, r, follow),
                            in_axes=(None, 0, 0, 0, None)))


def hanging_step(rewards: np.ndarray, max_reward: float, last: int) -> int | None:
    """The first agent step t <= ``last`` whose reward (T,) is under ``max_reward``, or None."""
    steps = np.flatnonzero(np.asarray(rewards)[: last + 1] < max_reward)
    return int(steps[0]) if steps.size else None


def discounted(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """sum_t gamma^t r_t over the last axis of ``rewards`` (..., T), in float64."""
    rewards = np.asarray(rewards, np.float64)
    return rewards @ gamma ** np.arange(rewards.shape[-1])


def average_ranks(values: np.ndarray, decimals: int = 6) -> np.ndarray:
    """Ranks (n,) of ``values`` (n,) from 0, tied values (equal to ``decimals`` places) sharing their mean rank."""
    rounded = np.round(np.asarray(values, np.float64), decimals)
    order = np.argsort(rounded, kind="stable")
    ranks = np.empty(len(rounded))
    ranks[order] = np.arange(len(rounded))
    _, tie, counts = np.unique(rounded, return_inverse=True, return_counts=True)
    return np.bincount(tie, weights=ranks)[tie] / counts[tie]


def rank_correlation(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation of two samples (n,), ties (to 6 decimals: returns that differ by round-off) at
    their mean rank; NaN where either sample is constant."""
    rx, ry = average_ranks(x), average_ranks(y)
    if np.ptp(rx) == 0 or np.ptp(ry) == 0:
        return float("nan")
    return float(np.corrcoef(rx, ry)[0, 1])


def elite_ranks(num_elites: int, count: int) -> np.ndarray:
    """``count`` ranks spread evenly from 0 (the best elite) to ``num_elites - 1``; ConfigError when ``count`` is
    not in [2, num_elites]."""
    if not 2 <= count <= num_elites:
        raise ConfigError(f"--elites must be an integer in [2, {num_elites}] (the planner's num_elites), got {count}")
    return np.round(np.linspace(0, num_elites - 1, count)).astype(np.int32)


def analyse(agent: Any, agent_state: Any, env: Any, key: jax.Array, episodes: int, count: int, follow: int,
            max_reward: float, progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """The command's rows (:data:`COLUMNS`) for one trained seed's ``agent_state``: the episodes ``cli eval`` plays
    with ``key``, from each one's first hanging step (none from an episode that never hangs early enough)."""
    from lnnmpc.train.evaluate import SameProgram
    from lnnmpc.train.loop import evaluation_keys

    planner = agent.config.planner
    ranks = elite_ranks(planner.num_elites, count)
    last = env.episode_length - planner.horizon - follow
    if last < 0:
        raise ConfigError(f"--follow {follow} plus the plan's {planner.horizon} steps exceed the episode's "
                          f"{env.episode_length} agent steps")
    pair = SameProgram(agent, env)
    states, carries, rewards = _trace_program(pair, episodes)(agent_state, key)
    picks = [(e, t) for e in range(episodes)
             if (t := hanging_step(np.asarray(rewards[:, e]), max_reward, last)) is not None]
    if not picks:
        return []
    episode, step = (np.array(x) for x in zip(*picks, strict=True))
    pick = lambda x: x[step, episode]  # noqa: E731  (T, episodes, ...) -> (picks, ...)
    plan_keys = jax.vmap(jax.random.fold_in)(evaluation_keys(key, episodes)[1][episode], jnp.asarray(step))
    with reporting(progress, follow):
        predicted, paid = jax.block_until_ready(_rollout_program(pair, follow)(
            agent_state, jax.tree_util.tree_map(pick, states), jax.tree_util.tree_map(pick, carries), plan_keys,
            jnp.asarray(ranks)))
    predicted, paid = np.asarray(predicted, np.float64), np.asarray(paid, np.float64)
    return [{"episode": int(e), "t": int(t), "rank": int(r), "predicted": float(predicted[i, j]),
             "paid": float(discounted(paid[i, j], planner.gamma)), "paid_sum": float(paid[i, j].sum())}
            for i, (e, t) in enumerate(picks) for j, r in enumerate(ranks)]


def markdown(rows: list[dict]) -> str:
    """One table row per episode: t*, the predicted values' range, the paid returns' range and standard deviation,
    and their rank correlation."""
    lines = ["| episode | t | elites | predicted: best - worst | paid: max - min | paid: std | rank correlation |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    for episode in sorted({r["episode"] for r in rows}):
        mine = [r for r in rows if r["episode"] == episode]
        predicted, paid = (np.array([r[k] for r in mine]) for k in ("predicted", "paid"))
        lines.append(f"| {episode} | {mine[0]['t']} | {len(mine)} | {predicted.max() - predicted.min():.3f} | "
                     f"{np.ptp(paid):.1f} | {paid.std():.1f} | {rank_correlation(predicted, paid):+.2f} |")
    return "\n".join(lines) + "\n"


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command's options (module docstring)."""
    p = argparse.ArgumentParser(prog="python -m lnnmpc.analysis.elite_outcomes",
                                description=__doc__.split("\n")[0])
    p.add_argument("run", help="run folder (config.json and a checkpoint, policy.npz or policies/)")
    p.add_argument("--checkpoint", type=int, default=None, help="environment step of the policy (default newest)")
    p.add_argument("--episodes", type=int, default=4, help="episodes (default 4), as `cli eval` plays them")
    p.add_argument("--seed", type=int, default=0, help="the episodes' key, as `cli eval --seed` (default 0)")
    p.add_argument("--elites", type=int, default=16, help="elite ranks played from each hanging step (default 16)")
    p.add_argument("--follow", type=int, default=60, help="agent steps of the agent's acting after the elite's")
    p.add_argument("--max-reward", type=float, default=0.1, help="an agent step's reward under it: hanging")
    p.add_argument("--out", default=None, help="also write one row per elite to this CSV")
    return p.parse_args(argv)


def run_analysis(args: argparse.Namespace) -> str:
    """Plays, summarises, writes (with ``--out``) and returns the printed table (ConfigError for bad input)."""
    from lnnmpc.train import runfolder
    from lnnmpc.train.config import require_int
    from lnnmpc.train.evaluate import check_observation_size, load_policy
    from lnnmpc.train.report import StepProgress
    from lnnmpc.train.setup import config_env

    require_int("episodes", args.episodes, 1)
    require_int("follow", args.follow, 1)
    policy = load_policy(args.run, args.checkpoint)
    env = config_env(policy.config, policy.config.eval_obs)
    check_observation_size(env, policy)
    agent = policy.loop.agent
    if not hasattr(agent, "act_planned"):
        raise ConfigError(f"{args.run!r}: {type(agent).__name__} does not plan with MPPI (no act_planned)")
    key = jax.random.split(jax.random.key(args.seed), policy.config.seeds)[0]  # cli eval's key of trained seed 0
    rows = analyse(agent, policy.seed_state(0), env, key, args.episodes, args.elites, args.follow, args.max_reward,
                   progress=StepProgress(f"agent steps after the elites' plans, {args.run}"))
    if not rows:
        return f"no episode hangs (a reward under {args.max_reward:g}) early enough to follow\n"
    if args.out:
        runfolder.write_csv(args.out, list(COLUMNS), rows)
    return markdown(rows)


def main(argv: Sequence[str] | None = None) -> int:
    from lnnmpc.train.config import command_status

    args = parse_args(argv)
    return command_status(lambda: run_analysis(args))


if __name__ == "__main__":
    sys.exit(main())
