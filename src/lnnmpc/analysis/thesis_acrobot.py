"""``python -m lnnmpc.analysis.thesis_acrobot``: the thesis's acrobot reward (its eq. 4.6) beside dm_control's.

    python -m lnnmpc.analysis.thesis_acrobot [--episodes 10] [--steps 1000] [--out CSV]

The thesis states the acrobot-swingup reward as (§4.1, eq. 4.6)

    R = 0.5 |cos θ1| + 0.5 |cos θ2|

(θ1 the shoulder's angle from the vertical, θ2 the elbow's; the equation's ``clip(·, ε_radius)`` has no stated
bound and is left out), while dm_control's task, which SPEC §2 makes ours, pays ``rewards.tolerance`` of the tip's
distance to a target above the shoulder. Under eq. 4.6 a chain hanging at rest earns the full reward of 1 per
step, as an upright one does; under dm_control's reward it earns ~0. So a controller that only takes the energy out
of the links scores high on the thesis's reward and nothing on dm_control's.

This module plays dm_control's acrobot-swingup (the original simulator, CPU, one control step at a time, 1000 per
episode, no action repeat) with reference controllers that never try to swing up:

* ``zero``: no torque;
* ``uniform``: uniform random torques in [-1, 1];
* ``elbow-damping``: the torque -k·(elbow velocity), clipped to [-1, 1] (k = 1), which brakes the links.

It writes one row per (controller, episode) with both returns (``--out``, default
``acrobot_thesis_reward.csv``) and prints their mean ± std per controller as a markdown table. Episode ``i`` uses
dm_control's ``task_kwargs={"random": i}`` (the same initial states for every controller). Compare the thesis's
Table 5.3, where cfc-zp-det scores 883.1 ± 0.2 on acrobot-swingup (TD-MPC2 329.0).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence

import numpy as np

Controller = Callable[[object], np.ndarray]  # dm_control physics -> action (1,)


def thesis_reward(shoulder: np.ndarray, elbow: np.ndarray) -> np.ndarray:
    """The thesis's eq. 4.6 at joint angles ``shoulder``, ``elbow`` (radians, any equal shapes; 0 = upright, as in
    dm_control's acrobot): 0.5 |cos θ1| + 0.5 |cos θ2|, float64, in [0, 1]."""
    return 0.5 * np.abs(np.cos(np.asarray(shoulder, np.float64))) + 0.5 * np.abs(np.cos(np.asarray(elbow, np.float64)))


def elbow_damping(gain: float = 1.0) -> Controller:
    """The controller that brakes the elbow: torque -``gain`` · elbow velocity, clipped to [-1, 1]."""
    if not gain > 0:
        raise ValueError(f"gain must be > 0, got {gain}")
    return lambda physics: np.clip([-gain * float(physics.named.data.qvel["elbow"][0])], -1.0, 1.0)


def controllers(seed: int) -> dict[str, Controller]:
    """The reference controllers by name (module docstring); ``seed`` seeds the uniform one's torques."""
    rng = np.random.default_rng(seed)
    return {"zero": lambda physics: np.zeros(1),
            "uniform": lambda physics: rng.uniform(-1.0, 1.0, size=1),
            "elbow-damping": elbow_damping(1.0)}


CONTROLLERS = tuple(controllers(0))
EPISODE_STEPS = 1000  # dm_control's acrobot-swingup episode, in control steps


def play(controller: Controller, episode: int, steps: int = EPISODE_STEPS) -> tuple[float, float]:
    """One dm_control acrobot-swingup episode of ``steps`` control steps (initial state ``random=episode``) under
    ``controller``: (dm_control's return, the return under :func:`thesis_reward` of each step's resulting angles)."""
    from dm_control import suite

    env = suite.load("acrobot", "swingup", task_kwargs={"random": episode})
    env.reset()
    dm_return = thesis_return = 0.0
    for _ in range(steps):
        step = env.step(controller(env.physics))
        dm_return += float(step.reward)
        qpos = env.physics.named.data.qpos
        thesis_return += float(thesis_reward(qpos["shoulder"][0], qpos["elbow"][0]))
    return dm_return, thesis_return


def score(names: Sequence[str], episodes: int, steps: int = EPISODE_STEPS,
          progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """Rows {controller, episode, dm_control_return, thesis_return} for each controller in ``names`` and episode
    0..``episodes``-1; ``progress(done, total)`` after each episode."""
    unknown = sorted(set(names) - set(CONTROLLERS))
    if unknown:
        raise ValueError(f"unknown controller(s) {unknown}; known: {list(CONTROLLERS)}")
    if episodes < 1 or not 1 <= steps <= EPISODE_STEPS:
        raise ValueError(f"episodes must be >= 1 and steps in 1..{EPISODE_STEPS} (dm_control's episode), "
                         f"got episodes={episodes}, steps={steps}")
    rows = []
    for name in names:
        for episode in range(episodes):
            controller = controllers(episode)[name]
            dm_return, thesis_return = play(controller, episode, steps)
            rows.append({"controller": name, "episode": episode, "dm_control_return": dm_return,
                         "thesis_return": thesis_return})
            if progress is not None:
                progress(len(rows), len(names) * episodes)
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Per controller, in order of first appearance: episodes and mean/std of both returns."""
    out = []
    for name in dict.fromkeys(row["controller"] for row in rows):
        dm = np.array([row["dm_control_return"] for row in rows if row["controller"] == name])
        thesis = np.array([row["thesis_return"] for row in rows if row["controller"] == name])
        out.append({"controller": name, "episodes": len(dm), "dm_control": f"{dm.mean():.1f} ± {dm.std():.1f}",
                    "thesis": f"{thesis.mean():.1f} ± {thesis.std():.1f}"})
    return out


def main(argv: Sequence[str] | None = None) -> int:
    from lnnmpc.analysis.episodes import markdown_table
    from lnnmpc.train import runfolder
    from lnnmpc.train.report import StepProgress

    parser = argparse.ArgumentParser(prog="python -m lnnmpc.analysis.thesis_acrobot",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=10, help="episodes per controller (default 10)")
    parser.add_argument("--steps", type=int, default=EPISODE_STEPS,
                        help=f"control steps per episode, at most {EPISODE_STEPS} (default all)")
    parser.add_argument("--controllers", default=",".join(CONTROLLERS),
                        help=f"comma-separated, of {', '.join(CONTROLLERS)} (default all)")
    parser.add_argument("--out", default="acrobot_thesis_reward.csv", help="CSV path")
    args = parser.parse_args(argv)
    try:
        rows = score(args.controllers.split(","), args.episodes, args.steps, StepProgress("dm_control episodes"))
    except ValueError as error:
        parser.error(str(error))
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    runfolder.write_csv(args.out, list(rows[0]), rows)
    print(markdown_table(summary(rows), (("controller", "controller", ""), ("episodes", "episodes", "d"),
                                         ("dm_control return", "dm_control", ""), ("eq. 4.6 return", "thesis", ""))))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
