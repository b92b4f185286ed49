"""``python -m lnnmpc.analysis.acrobot RUN``: what an acrobot agent does with its two links, seed by seed.

    python -m lnnmpc.analysis.acrobot <run folder> [--checkpoint STEP] [--episodes 4] [--length T]

Plays deterministic episodes (the trainer's evaluation protocol, :func:`lnnmpc.analysis.rollout.rollout`; the same
key for every seed) with each trained seed of an acrobot run and reports what a return alone does not say:

* ``shoulder_turns``, ``elbow_turns``: full turns of each joint per episode (the unwrapped angle's total
  variation / 2π); a policy that swings up and balances turns each link about half a turn, one that whirls the
  links through the top several;
* ``tip_above_share``: the share of agent steps with the tip above the shoulder (swung up);
* ``target_share``: the share with the tip inside the target sphere (radius 0.2), where acrobot-swingup-sparse
  pays and acrobot-swingup pays fully;
* ``longest_target_stay``: the longest run of consecutive agent steps in the target, as a share of the episode:
  balancing shows as one long stay, whirling as many short passes;
* ``before_target_share``: the share of the episode before the tip first enters the target (1: never); with one
  long stay to the end it is the swing-up's time, the return's main cost;
* ``mean_tip_distance``: the mean distance of the tip from the target;
* ``thesis_reward_mean``: the mean per agent step of the thesis's acrobot reward (its eq. 4.6,
  :func:`lnnmpc.analysis.thesis_acrobot.thesis_reward`), which pays a hanging chain as fully as an upright one;
  x 1000 it estimates the episode's return under that reward (no torque at all: ~0.79).

The tip comes from MuJoCo's kinematics of dm_control's acrobot model at each recorded joint position (qpos = 0:
both links upright, the tip on the target). Writes ``<run>/analysis/<step>/acrobot_episodes.csv`` (or ``--out``;
one row per seed, means over the episodes), beside it ``acrobot_episodes.png`` (each seed's episodes over time: the
tip's height above the shoulder and its distance to the target, the target shaded) and prints the rows as a
markdown table.
"""

from __future__ import annotations

import sys

import numpy as np

from lnnmpc.analysis import episodes as episodes_
from lnnmpc.analysis.thesis_acrobot import thesis_reward

COLUMNS: tuple[episodes_.Column, ...] = (
    ("shoulder turns", "shoulder_turns", ".1f"), ("elbow turns", "elbow_turns", ".1f"),
    ("tip above shoulder", "tip_above_share", ".3f"), ("in target", "target_share", ".3f"),
    ("longest stay in target", "longest_target_stay", ".3f"), ("before first in target", "before_target_share", ".3f"),
    ("mean tip distance", "mean_tip_distance", ".2f"),
    ("eq. 4.6 reward per step", "thesis_reward_mean", ".3f"))
STATS = tuple(key for _, key, _ in COLUMNS)


def tip_positions(qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """MuJoCo kinematics of the acrobot at joint positions ``qpos`` (..., 2) = [shoulder, elbow]: the tip's
    position (..., 3), the shoulder's (3,), the target's (3,) and the target's radius."""
    import mujoco

    from lnnmpc.train.setup import shared_env

    model = shared_env("acrobot-swingup", "fast", {}).mj_model  # the process's Env of the task, not a new one
    data = mujoco.MjData(model)
    flat = np.asarray(qpos, np.float64).reshape(-1, 2)
    tips = np.empty((len(flat), 3))
    for i, q in enumerate(flat):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        tips[i] = data.site("tip").xpos
    shoulder = np.array(data.body("upper_arm").xpos)
    return (tips.reshape(*np.shape(qpos)[:-1], 3), shoulder, np.array(data.site("target").xpos),
            float(model.site_size[model.site("target").id, 0]))


def longest_stay(inside: np.ndarray) -> np.ndarray:
    """The longest run of consecutive True along the last axis of ``inside`` (E, T), in steps (E,)."""
    best = np.zeros(inside.shape[0], dtype=np.int64)
    run = np.zeros(inside.shape[0], dtype=np.int64)
    for column in np.asarray(inside, bool).T:
        run = np.where(column, run + 1, 0)
        best = np.maximum(best, run)
    return best


def episode_stats(qpos: np.ndarray) -> dict[str, np.ndarray]:
    """Per-episode statistics (each (E,)) of acrobot joint positions ``qpos`` (E, T, 2): [shoulder, elbow] angles
    at each agent step (module docstring)."""
    qpos = np.asarray(qpos, dtype=np.float64)
    if qpos.ndim != 3 or qpos.shape[-1] != 2:
        raise ValueError(f"qpos must be (episodes, steps, 2) = [shoulder angle, elbow angle], got {qpos.shape}")
    turns = np.abs(np.diff(np.unwrap(qpos, axis=1), axis=1)).sum(axis=1) / (2 * np.pi)
    tips, shoulder, target, radius = tip_positions(qpos)
    distance = np.linalg.norm(tips - target, axis=-1)
    inside = distance <= radius
    first_inside = np.where(inside.any(axis=1), inside.argmax(axis=1), qpos.shape[1])
    return {"shoulder_turns": turns[:, 0], "elbow_turns": turns[:, 1],
            "tip_above_share": (tips[..., 2] > shoulder[2]).mean(axis=1), "target_share": inside.mean(axis=1),
            "longest_target_stay": longest_stay(inside) / qpos.shape[1],
            "before_target_share": first_inside / qpos.shape[1], "mean_tip_distance": distance.mean(axis=1),
            "thesis_reward_mean": thesis_reward(qpos[..., 0], qpos[..., 1]).mean(axis=1)}


def episode_traces(qpos: np.ndarray) -> list[episodes_.Trace]:
    """The figure's traces of acrobot joint positions ``qpos`` (E, T, 2): the tip's height above the shoulder (the
    target's band shaded: its centre 2 above the shoulder, ± its radius) and its distance to the target (inside
    the radius shaded)."""
    tips, shoulder, target, radius = tip_positions(np.asarray(qpos, dtype=np.float64))
    top = float(target[2] - shoulder[2])
    return [episodes_.Trace("tip height above the shoulder", tips[..., 2] - shoulder[2], (top - radius, top + radius)),
            episodes_.Trace("tip distance to the target", np.linalg.norm(tips - target, axis=-1), (0.0, radius))]


def main(argv: list[str] | None = None) -> int:
    return episodes_.analysis_main(argv, prog="python -m lnnmpc.analysis.acrobot", description=__doc__.split("\n")[0],
                                   domain="acrobot", filename="acrobot_episodes.csv", columns=COLUMNS,
                                   episode_stats=episode_stats, episode_traces=episode_traces, shaded="the target")


if __name__ == "__main__":
    sys.exit(main())
