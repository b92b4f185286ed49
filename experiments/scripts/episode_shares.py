"""How much of the spread of evaluation returns is the episode's initial state, how much the policy.

    python experiments/scripts/episode_shares.py CSV [CSV ...]

Each CSV is one policy's evaluation (``python -m lnnmpc.train.cli eval ... --out CSV``) over the same episodes
(the same ``--seed``, backend and episode count, so episode e starts from the same initial state in every file;
read and checked as ``python -m lnnmpc.train.paired`` reads them).
The returns form a (policies, episodes) table; the sums of squares split as in a two-way analysis of variance
without replication: the episode's share (the spread of the per-episode means over policies), the policy's share
(the spread of the per-policy means) and the rest. Prints the shares, the per-episode mean over policies, the best
policy's return on each episode and the mean of those bests (what picking the best policy per initial state would
score).
"""

from __future__ import annotations

import sys

import numpy as np


def returns_table(paths: list[str]) -> np.ndarray:
    """(policies, episodes) returns, one row per CSV (:func:`lnnmpc.train.paired.read_episode_returns`), the
    columns the first CSV's (seed, episode) rows in order; every CSV must hold the same episodes
    (:func:`lnnmpc.train.paired.check_same_episodes`, ConfigError otherwise)."""
    from lnnmpc.train.paired import check_same_episodes, read_episode_returns

    csvs = [read_episode_returns(path) for path in paths]
    for other in csvs[1:]:
        check_same_episodes(csvs[0], other)
    keys = sorted(csvs[0].returns)
    return np.stack([c.values(keys) for c in csvs])


def shares(table: np.ndarray) -> dict[str, float]:
    """The episode's, the policy's and the residual share of the total sum of squares of ``table`` (P, E)."""
    grand = table.mean()
    total = ((table - grand) ** 2).sum()
    episode = table.shape[0] * ((table.mean(axis=0) - grand) ** 2).sum()
    policy = table.shape[1] * ((table.mean(axis=1) - grand) ** 2).sum()
    return {"episode": episode / total, "policy": policy / total, "rest": 1 - (episode + policy) / total}


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print("give two or more evaluation CSVs of the same episodes", file=sys.stderr)
        return 2
    from lnnmpc.train.config import ConfigError

    try:
        table = returns_table(argv)
    except ConfigError as error:
        print(error, file=sys.stderr)
        return 2
    split = shares(table)
    print(f"{table.shape[0]} policies x {table.shape[1]} episodes: episode share {split['episode']:.2f}, policy share "
          f"{split['policy']:.2f}, rest {split['rest']:.2f}")
    print("per-episode mean over policies:", " ".join(f"{v:.0f}" for v in table.mean(axis=0)))
    print("best policy per episode:      ", " ".join(f"{v:.0f}" for v in table.max(axis=0)),
          f"(mean {table.max(axis=0).mean():.1f})")
    print("policy means:", " ".join(f"{v:.1f}" for v in table.mean(axis=1)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
