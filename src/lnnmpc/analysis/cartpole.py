"""``python -m lnnmpc.analysis.cartpole RUN``: where a cartpole agent keeps its pole and its cart, seed by seed.

    python -m lnnmpc.analysis.cartpole <run folder> [--checkpoint STEP] [--episodes 4] [--length T]

Plays deterministic episodes (the trainer's evaluation protocol, :func:`lnnmpc.analysis.rollout.rollout`; the same
key for every seed) with each trained seed of a cartpole run and reports what a return alone does not say:

* ``turns``: full turns of the pole per episode (the unwrapped hinge angle's total variation / 2π); a policy that
  swings up and balances turns about half a turn, one that spins the pole several;
* ``upright_share``: the share of agent steps with the pole upright (cos θ > 0.995, the sparse task's bound);
* ``sparse_region_share``: the share with the pole upright and the cart within ±0.25 as well, the region where
  cartpole-swingup-sparse pays (:data:`lnnmpc.envs.tasks.CART_BOUNDS`, :data:`UPRIGHT_COSINE_BOUNDS`);
* ``mean_abs_cart``: the mean |cart position|.

A seed stuck without the sparse reward spins the pole through the upright region (several turns, a few per cent of
its steps in the region); one that balances off centre has many upright steps but fewer in the region. Writes
``<run>/analysis/<step>/cartpole_episodes.csv`` (or ``--out``; one row per seed, means over the episodes), beside
it ``cartpole_episodes.png`` (each seed's episodes over time: the pole's cos θ and the cart position, the sparse
task's region shaded) and prints the rows as a markdown table.
"""

from __future__ import annotations

import sys

import numpy as np

from lnnmpc.analysis import episodes as episodes_
from lnnmpc.envs.tasks import CART_BOUNDS, UPRIGHT_COSINE_BOUNDS

COLUMNS: tuple[episodes_.Column, ...] = (
    ("turns", "turns", ".1f"), ("upright share", "upright_share", ".3f"),
    ("sparse region share", "sparse_region_share", ".3f"), ("mean abs cart", "mean_abs_cart", ".2f"))
STATS = tuple(key for _, key, _ in COLUMNS)


def episode_stats(qpos: np.ndarray) -> dict[str, np.ndarray]:
    """Per-episode statistics (each (E,)) of cartpole joint positions ``qpos`` (E, T, 2): [cart position, hinge
    angle] at each agent step (module docstring)."""
    qpos = np.asarray(qpos, dtype=np.float64)
    if qpos.ndim != 3 or qpos.shape[-1] != 2:
        raise ValueError(f"qpos must be (episodes, steps, 2) = [cart position, hinge angle], got {qpos.shape}")
    cart, angle = qpos[..., 0], qpos[..., 1]
    upright = np.cos(angle) >= UPRIGHT_COSINE_BOUNDS[0]
    centred = (cart >= CART_BOUNDS[0]) & (cart <= CART_BOUNDS[1])
    turning = np.abs(np.diff(np.unwrap(angle, axis=1), axis=1)).sum(axis=1)
    return {"turns": turning / (2 * np.pi), "upright_share": upright.mean(axis=1),
            "sparse_region_share": (upright & centred).mean(axis=1), "mean_abs_cart": np.abs(cart).mean(axis=1)}


def episode_traces(qpos: np.ndarray) -> list[episodes_.Trace]:
    """The figure's traces of cartpole joint positions ``qpos`` (E, T, 2): the pole's cos θ (upright band shaded)
    and the cart position (the sparse task's ±0.25 shaded)."""
    qpos = np.asarray(qpos, dtype=np.float64)
    return [episodes_.Trace("pole cos θ", np.cos(qpos[..., 1]), (UPRIGHT_COSINE_BOUNDS[0], 1.0)),
            episodes_.Trace("cart position", qpos[..., 0], tuple(CART_BOUNDS))]


def main(argv: list[str] | None = None) -> int:
    return episodes_.analysis_main(argv, prog="python -m lnnmpc.analysis.cartpole", description=__doc__.split("\n")[0],
                                   domain="cartpole", filename="cartpole_episodes.csv", columns=COLUMNS,
                                   episode_stats=episode_stats, episode_traces=episode_traces,
                                   shaded="the sparse task's region")


if __name__ == "__main__":
    sys.exit(main())
