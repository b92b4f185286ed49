"""``python -m lnnmpc.analysis.acrobot_ceiling``: what return dm_control's acrobot-swingup allows at all.

    python -m lnnmpc.analysis.acrobot_ceiling [--episodes 10] [--first-episode 0] [--horizon 100] [--samples 512]
        [--iterations 3] [--elites 64] [--knot 5] [--energy-weight 0.1] [--height-weight 0.1] [--out CSV]

Issue #5 asks cfc-zp-det for 700 on acrobot-swingup; the learned agents' best is 481.1 (RESULTS.md [77]) and they
score least where an episode starts hanging down. Is 700 within what the task allows? This module answers with a
strong model-based controller: sampling-based receding-horizon planning (MPPI over smooth action sequences, the
mean warm-started by shifting) on the acrobot's exact equations of motion, long horizons (100 agent steps = 2 s by
default), and no learning. It acts in dm_control itself (the original simulator, CPU): each agent step reads the
physics state, plans from it, and holds the planned action for ``--action-repeat`` control steps, as the agents
are evaluated with ``eval --backend dm_control``. Episode ``e`` starts where dm_control's ``task_kwargs={"random":
e}`` puts it, the starts of that evaluation. Any return it reaches is a return the task allows (a lower bound on
the best possible), so if it clears 700 the bar is reachable; if a planner this strong stays under it, the bar is
at least very hard.

The dynamics (``acrobot_physics.acrobot_accel``, ``rk4_step``) are the two-link chain's Lagrangian equations with the
masses, centres of mass, inertias, joint damping, gear and time step read from dm_control's model, integrated as
MuJoCo's RK4 does; tests hold them to MuJoCo's own steps in float64. The planner's score is the task's reward
(:func:`tip_reward`, dm_control's ``tolerance`` of the tip's distance to the target) plus ``--energy-weight``
times the closeness of the mechanical energy to the upright's at rest and ``--height-weight`` times the tip's
height, which let it pump energy where the task's reward, ~1e-14 hanging down, ranks nothing; the returns
reported are dm_control's own rewards only. Measured (RESULTS.md [81]): 559.2 on the evaluation's starts 0-9 and
571.8 over starts 0-39 with these defaults; a 3 s horizon with 1024 samples and 4 iterations scored lower (442.7).
It is no ceiling: the ``acrobot`` recipe acting every 4 control steps scores 588.3 on starts 0-9 over three final
policies, above this planner on 9 of the 10 (RESULTS.md [84]).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from lnnmpc.analysis.acrobot_physics import (
    EPISODE_STEPS,
    AcrobotParams,
    mechanical_energy,
    params_from_model,
    rk4_step,
    tip_reward,
)


class PlannerConfig(NamedTuple):
    """Receding-horizon MPPI over action sequences of ``horizon`` agent steps: ``samples`` sequences per
    iteration (noise drawn at knots every ``knot`` agent steps and linearly interpolated between them, so a
    sequence is smooth), ``elites`` best of them averaged with weights ``exp((score - best) / (temperature *
    spread))``, ``iterations`` refits per agent step; ``energy_weight`` and ``height_weight`` scale the shaping
    terms of the score (:func:`sequence_scores`)."""

    horizon: int = 100
    samples: int = 512
    iterations: int = 3
    elites: int = 64
    knot: int = 5
    temperature: float = 0.1
    std_init: float = 1.0
    std_min: float = 0.05
    energy_weight: float = 0.1
    height_weight: float = 0.1
    action_repeat: int = 2

    def validate(self) -> None:
        """Raises ValueError naming the first impossible value."""
        for name in ("horizon", "samples", "iterations", "elites", "knot", "action_repeat"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.elites > self.samples:
            raise ValueError(f"elites ({self.elites}) must not exceed samples ({self.samples})")
        if not (self.temperature > 0 and self.std_init > 0 and 0 < self.std_min <= self.std_init):
            raise ValueError(f"need temperature > 0 and 0 < std_min <= std_init, got {self.temperature}, "
                             f"{self.std_min} and {self.std_init}")
        if self.energy_weight < 0 or self.height_weight < 0:
            raise ValueError(f"energy_weight and height_weight must be >= 0, got {self.energy_weight} and "
                             f"{self.height_weight}")


def energy_bounds(p: AcrobotParams) -> tuple[float, float]:
    """Mechanical energy at rest hanging down and at rest upright (:func:`mechanical_energy` at those states)."""
    up = p.g * (p.m1 * p.c1 + p.m2 * (p.l1 + p.c2))
    return -up, up


def shaping_terms(p: AcrobotParams, qpos, qvel):
    """The planner's shaping terms ``(closeness, height)``, each ``(...)``, of angles and velocities ``(..., 2)``:
    ``1 - |E - E_up| / (E_up - E_down)`` (E the mechanical energy, E_up the upright's at rest, E_down hanging at
    rest) and the tip's height from its lowest (0) to its highest (1) point."""
    import jax.numpy as jnp

    down, up = energy_bounds(p)
    reach = p.l1 + 2 * p.c2
    height = 0.5 + 0.5 * (p.l1 * jnp.cos(qpos[..., 0]) + 2 * p.c2 * jnp.cos(qpos[..., 0] + qpos[..., 1])) / reach
    closeness = 1.0 - jnp.abs(mechanical_energy(p, qpos, qvel) - up) / (up - down)
    return closeness, height


def sequence_scores(p: AcrobotParams, config: PlannerConfig, qpos, qvel, actions):
    """Scores ``(N,)`` of action sequences ``(N, horizon)`` (each action held ``action_repeat`` control steps) from
    one state (``qpos``, ``qvel`` ``(2,)``): the sum over every control step of the task's reward, plus
    ``energy_weight`` times ``1 - |E - E_up| / (E_up - E_down)`` (E the mechanical energy, E_up the upright's at
    rest), plus ``height_weight`` times the tip's height from its lowest (0) to its highest (1) point."""
    import jax
    import jax.numpy as jnp

    def agent_step(carry, action):
        def control_step(state, _):
            q, v = rk4_step(p, *state, action)
            closeness, height = shaping_terms(p, q, v)
            return (q, v), (tip_reward(p, q) + config.energy_weight * closeness
                            + config.height_weight * height)

        carry, scores = jax.lax.scan(control_step, carry, None, length=config.action_repeat)
        return carry, scores.sum(axis=0)

    n = actions.shape[0]
    start = (jnp.broadcast_to(qpos, (n, 2)), jnp.broadcast_to(qvel, (n, 2)))
    _, per_step = jax.lax.scan(agent_step, start, actions.T)
    return per_step.sum(axis=0)


def smooth_noise(key, config: PlannerConfig):
    """Standard normal noise ``(samples, horizon)`` drawn at knots every ``knot`` steps and linearly
    interpolated between them."""
    import jax

    at_knots = jax.random.normal(key, (config.samples, knot_count(config.horizon, config.knot)))
    return interpolate_knots(at_knots, config.horizon, config.knot)


def knot_count(steps: int, knot: int) -> int:
    """Knots every ``knot`` steps that cover ``steps`` steps (both ends included)."""
    return -(-steps // knot) + 1


def interpolate_knots(at_knots, steps: int, knot: int):
    """Values ``(..., steps)`` linearly interpolated between values ``(..., knot_count(steps, knot))`` at knots
    every ``knot`` steps."""
    import jax.numpy as jnp

    pos = jnp.arange(steps) / knot
    left = jnp.floor(pos).astype(jnp.int32)
    frac = pos - left
    return at_knots[..., left] * (1 - frac) + at_knots[..., left + 1] * frac


def mppi_step(p: AcrobotParams, config: PlannerConfig, qpos, qvel, mean, key):
    """Plans from one state: ``iterations`` MPPI refits of ``mean`` ``(horizon,)`` and of a per-step std that
    starts at ``std_init`` (the first sample is always the mean itself). Returns the refitted mean; its first
    entry is the action to take."""
    import jax
    import jax.numpy as jnp

    def refit(carry, key):
        mean, std = carry
        noise = smooth_noise(key, config).at[0].set(0.0)
        actions = jnp.clip(mean + std * noise, -1.0, 1.0)
        scores = sequence_scores(p, config, qpos, qvel, actions)
        best, idx = jax.lax.top_k(scores, config.elites)
        spread = jnp.maximum(best[0] - best[-1], 1e-9)
        weights = jax.nn.softmax((best - best[0]) / (config.temperature * spread))
        elite = actions[idx]
        mean = weights @ elite
        std = jnp.sqrt(weights @ (elite - mean) ** 2)
        return (mean, jnp.clip(std, config.std_min, config.std_init)), best[0]

    std = jnp.full((config.horizon,), config.std_init)
    (mean, _), _ = jax.lax.scan(refit, (mean, std), jax.random.split(key, config.iterations))
    return mean


def plan_and_shift(p: AcrobotParams, config: PlannerConfig, qpos, qvel, mean, key):
    """One receding-horizon decision of one episode: the action (a scalar) to hold for the next agent step, and
    :func:`mppi_step`'s mean ``(horizon,)`` shifted by one step for the next decision (its last step repeated)."""
    import jax.numpy as jnp

    mean = mppi_step(p, config, qpos, qvel, mean, key)
    return mean[0], jnp.concatenate([mean[1:], mean[-1:]])


def make_planner(p: AcrobotParams, config: PlannerConfig):
    """A jitted ``plan(qpos, qvel, mean, key) -> (action, next mean)`` (:func:`plan_and_shift`) over episodes side
    by side (leading axis ``B``)."""
    import jax

    return jax.jit(jax.vmap(lambda qpos, qvel, mean, key: plan_and_shift(p, config, qpos, qvel, mean, key)))


def dm_control_envs(episodes: Sequence[int]):
    """dm_control acrobot-swingup environments, episode ``e`` reset with ``task_kwargs={"random": e}``."""
    from dm_control import suite

    envs = [suite.load("acrobot", "swingup", task_kwargs={"random": int(e)}) for e in episodes]
    for env in envs:
        env.reset()
    return envs


def play(envs, config: PlannerConfig, seed: int = 0, steps: int = EPISODE_STEPS, progress: bool = True
         ) -> list[dict]:
    """Plays ``steps`` control steps (an episode by default) in each (reset) dm_control environment side by side,
    planning every agent step from the physics' own state, and returns per episode its dm_control return, the
    first control step with the tip above the shoulder (-1: never), the control steps spent with the reward above
    0.9, and the start's angles."""
    import jax
    import jax.numpy as jnp

    if not 1 <= steps <= EPISODE_STEPS:
        raise ValueError(f"steps must be in [1, {EPISODE_STEPS}] (one dm_control episode), got {steps}")
    p = params_from_model(envs[0].physics.model.ptr)
    plan = make_planner(p, config)
    b = len(envs)
    starts = np.stack([np.array(env.physics.data.qpos) for env in envs])
    mean = jnp.zeros((b, config.horizon))
    key = jax.random.PRNGKey(seed)
    returns, near, first_above = np.zeros(b), np.zeros(b, int), np.full(b, -1)
    agent_steps = -(-steps // config.action_repeat)
    began = time.time()
    for step in range(agent_steps):
        qpos = jnp.asarray(np.stack([np.array(env.physics.data.qpos) for env in envs]))
        qvel = jnp.asarray(np.stack([np.array(env.physics.data.qvel) for env in envs]))
        key, sub = jax.random.split(key)
        action, mean = plan(qpos, qvel, mean, jax.random.split(sub, b))
        action = np.asarray(action)
        for i, env in enumerate(envs):
            for repeat in range(config.action_repeat):
                control = step * config.action_repeat + repeat
                if control >= steps:
                    break
                reward = env.step(np.array([action[i]])).reward
                returns[i] += reward
                near[i] += reward > 0.9
                tip_above = env.physics.named.data.site_xpos["tip", "z"] > env.physics.named.data.xpos["upper_arm", "z"]
                if tip_above and first_above[i] < 0:
                    first_above[i] = control
        if progress and (step + 1) % 25 == 0:
            print(f"  agent step {step + 1}/{agent_steps}: returns so far {np.round(returns, 1).tolist()} "
                  f"({time.time() - began:.0f} s)", file=sys.stderr, flush=True)
    return [{"return": float(returns[i]), "first_control_step_above_shoulder": int(first_above[i]),
             "control_steps_reward_above_0.9": int(near[i]), "start_shoulder": float(starts[i, 0]),
             "start_elbow": float(starts[i, 1])} for i in range(b)]


def episode_parser(description: str, defaults, episodes: int) -> argparse.ArgumentParser:
    """A command line with ``--episodes`` (default ``episodes``) and ``--first-episode`` (dm_control's starts) and
    one ``--name`` option per field of the config ``defaults`` (a NamedTuple; underscores as dashes)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--episodes", type=int, default=episodes, help="dm_control starts, episode e from random=e")
    parser.add_argument("--first-episode", type=int, default=0)
    for name, value in defaults._asdict().items():
        parser.add_argument(f"--{name.replace('_', '-')}", type=type(value), default=value)
    return parser


def checked_config(program: str, defaults, args):
    """The config of ``args``' options (fields of ``defaults``), validated with the episode range; ``None`` after
    printing the first impossible value, prefixed by ``program``, to stderr."""
    config = type(defaults)(**{name: getattr(args, name) for name in defaults._fields})
    try:
        config.validate()
        if args.episodes < 1 or args.first_episode < 0:
            raise ValueError(f"--episodes must be >= 1 and --first-episode >= 0, got {args.episodes} and "
                             f"{args.first_episode}")
    except ValueError as error:
        print(f"{program}: {error}", file=sys.stderr)
        return None
    return config


def main(argv: Sequence[str] | None = None) -> int:
    defaults = PlannerConfig()
    parser = episode_parser(__doc__.split("\n")[0], defaults, episodes=10)
    parser.add_argument("--seed", type=int, default=0, help="the planner's noise")
    parser.add_argument("--x64", action="store_true", help="plan in float64 (default float32, faster)")
    parser.add_argument("--out", default="acrobot_ceiling.csv")
    args = parser.parse_args(argv)
    config = checked_config("acrobot_ceiling", defaults, args)
    if config is None:
        return 2
    import jax

    jax.config.update("jax_enable_x64", args.x64)
    episodes = list(range(args.first_episode, args.first_episode + args.episodes))
    began = time.time()
    rows = play(dm_control_envs(episodes), config, seed=args.seed)
    seconds = time.time() - began
    with open(args.out, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["episode", *rows[0], *defaults._fields, "seed", "seconds"])
        writer.writeheader()
        for episode, row in zip(episodes, rows, strict=True):
            writer.writerow({"episode": episode, **row, **config._asdict(), "seed": args.seed,
                             "seconds": round(seconds, 1)})
    returns = np.array([row["return"] for row in rows])
    print("| episode | start (shoulder, elbow) | return | first control step above the shoulder |")
    print("|---|---|---:|---:|")
    for episode, row in zip(episodes, rows, strict=True):
        print(f"| {episode} | {row['start_shoulder']:.2f}, {row['start_elbow']:.2f} | {row['return']:.1f} | "
              f"{row['first_control_step_above_shoulder']} |")
    print(f"\nmean {returns.mean():.1f} ± {returns.std():.1f} over {len(rows)} episodes ({seconds:.0f} s); "
          f"rows in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
