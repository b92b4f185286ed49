"""Per-start acrobot-swingup returns against the start's mechanical energy: the planner on the exact physics
(``python -m lnnmpc.analysis.acrobot_ceiling``) beside learned policies played on the same dm_control starts.

    python experiments/scripts/acrobot_ceiling_figure.py --planner LABEL=CSV [LABEL=CSV ...]
        --policies LABEL=CSV [LABEL=CSV ...] --out PREFIX

A label may join several CSVs with ``+`` (``H100=a.csv+b.csv``: their episodes together). ``--planner`` CSVs
are ``acrobot_ceiling``'s (``episode``, ``return``, ``start_shoulder``, ``start_elbow``); ``--policies`` CSVs
are ``lnnmpc.train.cli eval --backend dm_control``'s (``episode``, ``return``), whose episode ``e`` starts where
``task_kwargs={"random": e}`` puts it, as the planner's does. Writes ``PREFIX.csv`` (one row per start: its
angles, its energy and every source's return, plus the best over all) and ``PREFIX.png``, and prints the means
over the starts they share.
"""

from __future__ import annotations

import argparse
import csv
import sys

import numpy as np


def read_returns(path: str) -> dict[int, float]:
    """Episode -> return of one CSV (the last row wins where an episode repeats)."""
    with open(path, newline="") as handle:
        return {int(row["episode"]): float(row["return"]) for row in csv.DictReader(handle)}


def start_energies(episodes: list[int]) -> dict[int, tuple[float, float, float]]:
    """Episode -> (shoulder, elbow, mechanical energy in J, 0 at the shoulder's height) of dm_control's start."""
    from lnnmpc.analysis import acrobot_ceiling as ac
    from lnnmpc.analysis import acrobot_physics as phys

    envs = ac.dm_control_envs(episodes)
    params = phys.params_from_model(envs[0].physics.model.ptr)
    out = {}
    for episode, env in zip(episodes, envs, strict=True):
        qpos, qvel = np.array(env.physics.data.qpos), np.array(env.physics.data.qvel)
        out[episode] = (float(qpos[0]), float(qpos[1]), float(phys.mechanical_energy(params, qpos, qvel)))
    return out


def labelled(items: list[str], flag: str) -> dict[str, str]:
    pairs = {}
    for item in items:
        label, sep, path = item.partition("=")
        if not sep or not label or not path:
            raise ValueError(f"{flag} takes LABEL=CSV, got {item!r}")
        pairs[label] = path
    return pairs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--planner", nargs="+", required=True)
    parser.add_argument("--policies", nargs="+", default=[])
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    try:
        planners, policies = labelled(args.planner, "--planner"), labelled(args.policies, "--policies")
    except ValueError as error:
        print(f"acrobot_ceiling_figure: {error}", file=sys.stderr)
        return 2
    sources = {**planners, **policies}
    returns = {label: {episode: value for part in path.split("+") for episode, value in read_returns(part).items()}
               for label, path in sources.items()}
    shared = sorted(set.intersection(*(set(r) for r in returns.values())))
    if not shared:
        print("acrobot_ceiling_figure: the CSVs share no episode", file=sys.stderr)
        return 2
    starts = start_energies(shared)
    rows = []
    for episode in shared:
        shoulder, elbow, energy = starts[episode]
        row = {"episode": episode, "start_shoulder": shoulder, "start_elbow": elbow, "start_energy": energy}
        row.update({label: returns[label][episode] for label in sources})
        row["best"] = max(returns[label][episode] for label in sources)
        rows.append(row)
    with open(f"{args.out}.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    for label in [*sources, "best"]:
        values = np.array([row[label] for row in rows])
        print(f"{label}: {values.mean():.1f} ± {values.std():.1f} over {len(rows)} starts")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lnnmpc.train.png import save_png

    energy = np.array([row["start_energy"] for row in rows])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label in planners:
        ax.plot(energy, [row[label] for row in rows], "o", ms=8, label=f"{label} (planner, exact physics)")
    for label in policies:
        ax.plot(energy, [row[label] for row in rows], "x", ms=7, label=f"{label} (learned policy)")
    ax.axhline(700, color="grey", ls="--", lw=1, label="issue #5's mean bar (700)")
    ax.set_xlabel("start's mechanical energy (J; hanging at rest -19.6, upright at rest +19.6)")
    ax.set_ylabel("dm_control return")
    ax.set_title("acrobot-swingup: return against the start's energy, dm_control starts")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, f"{args.out}.png", dpi=110)
    print(f"wrote {args.out}.csv and {args.out}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
