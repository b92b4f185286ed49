"""``python -m lnnmpc.analysis.plan_std``: how wide MPPI's search ends, and how alike its elites weigh, as agents act.

    python -m lnnmpc.analysis.plan_std RUN [RUN ...] [--checkpoint STEP] [--episodes 4] [--seed 0]
        [--floors 0.2,0.5] [--temperatures 0.167] [--out CSV]

While it trains, an agent adds ``max(std[0], explore_min_std)`` times the exploration noise to each planned action
(:mod:`lnnmpc.agents.mppi`): ``std[0]`` is the std of the first planned action when MPPI ends its search. The trainer
does not log it. This command plays a run's policy (the newest checkpoint, ``policy.npz`` or evaluation snapshot,
or ``--checkpoint``'s) for deterministic episodes on MJX under the run's evaluation corruptions: the episodes that
``cli eval --seed`` plays (each trained seed's key split from ``key(--seed)``;
:func:`lnnmpc.train.loop.play_episodes`). It records ``std[0]``, averaged over the action's dimensions, at every
agent step. For each run and trained seed it prints the std's 10th, 50th and 90th percentiles and the share of steps
under each of ``--floors``. That share is how often a floor of ``explore_min_std`` there would widen the
exploration noise. The episodes play without noise, so they visit the evaluation's states, not the exploring ones
of training.

It also keeps the values of MPPI's final elites at each step and prints the median of their effective number under
the planner's weighting, ``1 / sum(w^2)`` with ``w`` proportional to ``exp(temperature * (G - max G))``: near 1 the
weighting keeps one elite, near ``num_elites`` all of them; ``--temperatures`` adds the same median at other
temperatures (how soft the weighting would be, for the same elites).

``--out`` writes one row per agent step: run, seed, episode, t, std, reward, and the effective number of elites at
the planner's temperature (``ess_planner``) and at each of ``--temperatures`` (``ess_<temperature>``). A live line on
stderr counts each seed's agent steps as they are played (from inside the compiled program, so this program is not
kept in XLA's persistent cache: each process compiles it).
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

QUANTILES = (10, 50, 90)


class StdRecording:
    """``agent`` acting as usual, its carry extended by the planner's final ``std[0]`` (averaged over the action's
    dimensions, a scalar) and its final elites' values (num_elites,): ``(agent carry, std, elite values)``. Needs
    the agent's ``act_planned`` (MPPI's info)."""

    def __init__(self, agent: Any):
        if not hasattr(agent, "act_planned"):
            raise ValueError(f"{type(agent).__name__} does not plan with MPPI (no act_planned)")
        self.agent = agent

    def initial_carry(self) -> tuple[Any, jax.Array, jax.Array]:
        return self.agent.initial_carry(), jnp.zeros(()), jnp.zeros((self.agent.config.planner.num_elites,))

    def act(self, state, carry, obs, dt, key, *, explore: bool, first_step):
        """The agent's action (A,) and ``(its next carry, std[0].mean(), elite values)``."""
        action, nxt, info = self.agent.act_planned(state, carry[0], obs, dt, key, explore=explore,
                                                   first_step=first_step)
        return action, (nxt, info["std"][0].mean(), info["elite_values"].astype(carry[2].dtype))


def effective_elites(values: np.ndarray, temperature: float) -> np.ndarray:
    """The effective number of elites ``1 / sum(w^2)`` under MPPI's weights ``w`` proportional to
    ``exp(temperature * (G - max G))``, for elite values (..., num_elites) -> (...): 1 where one elite takes all
    the weight, num_elites where all weigh alike."""
    values = np.asarray(values, np.float64)
    weights = np.exp(temperature * (values - values.max(axis=-1, keepdims=True)))
    weights /= weights.sum(axis=-1, keepdims=True)
    return 1.0 / np.square(weights).sum(axis=-1)


@functools.lru_cache(maxsize=4)
def _std_program(pair: Any, episodes: int, steps: int | None):
    """The compiled episodes of ``pair`` (a :class:`lnnmpc.train.evaluate.SameProgram`: runs of one configuration
    share it, as their evaluations do), reporting each agent step done (:mod:`lnnmpc.train.step_report`)."""
    from lnnmpc.train.loop import play_episodes

    def record(state, carry, action, nxt):
        return carry[1], carry[2], nxt.reward

    return jax.jit(lambda s, k: play_episodes(StdRecording(pair.agent), s, pair.env, k, episodes, steps=steps,
                                              record=record, on_step=report_step))


def plan_std_episodes(agent: Any, agent_state: Any, env: Any, key: jax.Array, episodes: int,
                      steps: int | None = None, progress: Callable[[int, int], None] | None = None,
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Deterministic episodes of ``agent`` (one trained seed's ``agent_state``) on ``env``, as
    :func:`lnnmpc.train.loop.play_episodes` plays them; returns the returns (episodes,), the planner's std[0]
    (T, episodes), the rewards (T, episodes) and the final elites' values (T, episodes, num_elites).
    ``progress(done, total)`` is called as the (parallel) episodes' agent steps get done, from inside the compiled
    program (e.g. :class:`lnnmpc.train.report.StepProgress`)."""
    from lnnmpc.train.evaluate import SameProgram

    program = _std_program(SameProgram(agent, env), episodes, steps)
    with reporting(progress, steps or env.episode_length):
        returns, (std, elites, reward) = jax.block_until_ready(program(agent_state, key))
    return np.asarray(returns), np.asarray(std), np.asarray(reward), np.asarray(elites)


def std_summary(std: np.ndarray, floors: Sequence[float]) -> dict[str, float]:
    """Percentiles :data:`QUANTILES` of ``std`` (any shape) as ``p10``... and, per floor f, ``under_<f>``: the share
    of its values below f."""
    values = np.asarray(std, np.float64).ravel()
    if values.size == 0:
        raise ValueError("no std values to summarise")
    out = {f"p{q}": float(np.percentile(values, q)) for q in QUANTILES}
    out.update({f"under_{f:g}": float(np.mean(values < f)) for f in floors})
    return out


def markdown(rows: list[dict], floors: Sequence[float], temperatures: Sequence[float] = ()) -> str:
    """One table row per (run, seed): episodes, mean return, :func:`std_summary`'s numbers and the median effective
    number of elites at the planner's temperature (``ess_planner``) and at each of ``temperatures``."""
    head = ["run", "seed", "episodes", "return", *(f"std p{q}" for q in QUANTILES),
            *(f"share under {f:g}" for f in floors), "planner temperature", "elites p50",
            *(f"elites p50 at {t:g}" for t in temperatures)]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for r in rows:
        cells = [r["run"], str(r["seed"]), str(r["episodes"]), f"{r['return']:.1f}",
                 *(f"{r[f'p{q}']:.3f}" for q in QUANTILES), *(f"{r[f'under_{f:g}']:.2f}" for f in floors),
                 f"{r['temperature']:g}", f"{r['ess_planner']:.1f}", *(f"{r[f'ess_{t:g}']:.1f}" for t in temperatures)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def parse_positive_numbers(text: str, option: str) -> tuple[float, ...]:
    """``"0.2,0.5"`` -> (0.2, 0.5); ConfigError naming ``option`` for anything but positive finite numbers."""
    try:
        numbers = tuple(float(x) for x in text.split(","))
    except ValueError:
        numbers = ()
    if not numbers or not all(np.isfinite(f) and f > 0 for f in numbers):
        raise ConfigError(f"{option} takes positive numbers separated by commas, got {text!r}")
    return numbers


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command's options (module docstring)."""
    p = argparse.ArgumentParser(prog="python -m lnnmpc.analysis.plan_std", description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", help="run folders (config.json and a checkpoint, policy.npz or policies/)")
    p.add_argument("--checkpoint", type=int, default=None, help="environment step of the policy (default newest)")
    p.add_argument("--episodes", type=int, default=4, help="episodes per trained seed (default 4)")
    p.add_argument("--seed", type=int, default=0, help="the episodes' key, as `cli eval --seed` (default 0)")
    p.add_argument("--floors", default="0.2,0.5", help="explore_min_std values to count steps under")
    p.add_argument("--temperatures", default=None,
                   help="MPPI temperatures at which to count the final elites' effective number too, e.g. 0.167")
    p.add_argument("--out", default=None, help="also write every step to this CSV")
    return p.parse_args(argv)


def run_analysis(args: argparse.Namespace) -> str:
    """Plays, summarises, writes (with ``--out``) and returns the printed table (ConfigError for bad input)."""
    from lnnmpc.train import runfolder
    from lnnmpc.train.config import require_int
    from lnnmpc.train.evaluate import check_observation_size, load_policy
    from lnnmpc.train.report import StepProgress
    from lnnmpc.train.setup import config_env

    require_int("episodes", args.episodes, 1)
    floors = parse_positive_numbers(args.floors, "--floors")
    temperatures = () if args.temperatures is None else parse_positive_numbers(args.temperatures, "--temperatures")
    rows, steps = [], []
    for run in args.runs:
        policy = load_policy(run, args.checkpoint)
        env = config_env(policy.config, policy.config.eval_obs)
        check_observation_size(env, policy)
        try:
            StdRecording(policy.loop.agent)
        except ValueError as error:
            raise ConfigError(f"{run!r}: {error}") from None
        keys = jax.random.split(jax.random.key(args.seed), policy.config.seeds)  # cli eval's per-seed keys
        for seed in range(policy.config.seeds):
            unit = f"agent steps of {args.episodes} episodes, {run} seed {seed}"
            returns, std, reward, elites = plan_std_episodes(policy.loop.agent, policy.seed_state(seed), env,
                                                             keys[seed], args.episodes, progress=StepProgress(unit))
            own = policy.loop.agent.config.planner.temperature
            ess = {"ess_planner": effective_elites(elites, own),
                   **{f"ess_{t:g}": effective_elites(elites, t) for t in temperatures}}
            rows.append({"run": run, "seed": seed, "episodes": args.episodes, "return": float(returns.mean()),
                         **std_summary(std, floors), "temperature": own,
                         **{name: float(np.median(values)) for name, values in ess.items()}})
            steps += [{"run": run, "seed": seed, "episode": e, "t": t, "std": float(std[t, e]),
                       "reward": float(reward[t, e]), **{name: float(values[t, e]) for name, values in ess.items()}}
                      for e in range(std.shape[1]) for t in range(std.shape[0])]
    if args.out:
        ess_columns = ["ess_planner", *(f"ess_{t:g}" for t in temperatures)]
        runfolder.write_csv(args.out, ["run", "seed", "episode", "t", "std", "reward", *ess_columns], steps)
    return markdown(rows, floors, temperatures)


def main(argv: Sequence[str] | None = None) -> int:
    from lnnmpc.train.config import command_status

    args = parse_args(argv)
    return command_status(lambda: run_analysis(args))


if __name__ == "__main__":
    sys.exit(main())
