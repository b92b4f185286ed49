"""How often random actions alone reach cartpole-swingup-sparse's rewarded region, white noise against colored.

    .venv/bin/python experiments/scripts/random_exploration_sparse.py [--episodes 64] [--out CSV]

Plays ``--episodes`` full episodes (500 agent steps, action repeat 2) of cartpole-swingup-sparse on MJX per kind of
random action, every episode from its own initial state (the same initial states for every kind):

* ``uniform``: i.i.d. uniform in [-1, 1] (the trainer's seed phase);
* ``white``: i.i.d. Gaussian of std ``--scale``, clipped to [-1, 1] (what an MPPI planner whose value is flat
  executes: a random elite's first action plus its std times white noise, every step anew);
* ``pink`` / ``red``: Gaussian noise with power spectrum 1/f^β over the whole episode (β = 1 / 2; unit variance
  per episode, times ``--scale``, clipped), shaped as ``train --explore-noise-beta`` shapes it
  (:mod:`lnnmpc.agents.exploration`; the FFT method of Timmer & König 1995), as in "Pink noise is
  all you need" (Eberhard et al., ICLR 2023), which found such episode-long colored exploration noise to help most
  on sparse-reward dm_control tasks.

Prints, per kind, the share of episodes with any reward, the mean return and the mean share of agent steps in the
rewarded region (pole cos > 0.995 and |cart| < 0.25, :func:`lnnmpc.analysis.cartpole.episode_stats`), and the
mean number of pole turns; ``--out`` writes the same as CSV. The question it answers: can an agent whose value has
not seen a reward yet find the first one by its own noise, and does the noise's colour change that?
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc import envs
from lnnmpc.agents.exploration import shape_spectrum
from lnnmpc.analysis.cartpole import episode_stats
from lnnmpc.analysis.report import write_csv

KINDS = {"uniform": None, "white": 0.0, "pink": 1.0, "red": 2.0}


def episode_noise(rng: np.random.Generator, beta: float, episodes: int, steps: int) -> np.ndarray:
    """(episodes, steps) Gaussian sequences with power spectrum ∝ 1/f^β, each of unit variance: the trainer's
    :func:`lnnmpc.agents.exploration.shape_spectrum` of standard normal Fourier coefficients drawn by ``rng``."""
    shape = (episodes, steps // 2 + 1)  # drawn episode-major, the coefficients along axis 0 for shape_spectrum
    real, imag = rng.standard_normal(shape).T, rng.standard_normal(shape).T
    return np.asarray(shape_spectrum(jnp.asarray(real), jnp.asarray(imag), beta, steps), np.float64).T


def random_actions(kind: str, rng: np.random.Generator, episodes: int, steps: int, scale: float) -> np.ndarray:
    """(steps, episodes, 1) float32 actions in [-1, 1] of one kind (module docstring), time-major for the scan."""
    if kind == "uniform":
        actions = rng.uniform(-1.0, 1.0, (episodes, steps))
    else:
        actions = np.clip(scale * episode_noise(rng, KINDS[kind], episodes, steps), -1.0, 1.0)
    return actions.T[..., None].astype(np.float32)


def play(env, keys: jax.Array, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rewards (episodes, steps) and qpos (episodes, steps, 2) of episodes from ``keys`` under fixed ``actions``."""

    @jax.jit
    def episodes(keys, actions):
        def step(states, action):
            states = jax.vmap(env.step)(states, action)
            return states, (states.reward, states.physics.qpos)

        _, (rewards, qpos) = jax.lax.scan(step, jax.vmap(env.reset)(keys), actions)
        return rewards, qpos

    rewards, qpos = episodes(keys, jnp.asarray(actions))
    return np.asarray(rewards).T, np.swapaxes(np.asarray(qpos), 0, 1)


def lag1_autocorrelation(x: np.ndarray) -> float:
    """Mean over episodes of the lag-1 autocorrelation of sequences ``x`` (episodes, steps), each centred on its
    own mean."""
    x = x - x.mean(axis=1, keepdims=True)
    return float(((x[:, 1:] * x[:, :-1]).sum(axis=1) / np.maximum((x * x).sum(axis=1), 1e-12)).mean())


def outcome_columns(rewards: np.ndarray, qpos: np.ndarray) -> dict[str, float]:
    """A CSV row's outcome columns of episodes with ``rewards`` (episodes, steps) and joint positions ``qpos``
    (episodes, steps, 2): the share of episodes with any reward, the mean and largest return, and the mean of
    :func:`episode_stats`' sparse-region share and turns."""
    returns = rewards.sum(axis=1)
    stats = episode_stats(qpos)
    return {"share_with_reward": float((returns > 0).mean()), "mean_return": float(returns.mean()),
            "max_return": float(returns.max()), "sparse_region_share": float(stats["sparse_region_share"].mean()),
            "turns": float(stats["turns"].mean())}


def save_rows(rows: list[dict], path: str) -> None:
    """``rows`` as the CSV ``path`` (its folder made; written atomically), and a line saying so."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    write_csv(path, rows)
    print(f"-> {path}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--scale", type=float, default=1.0, help="std of the Gaussian kinds before clipping")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="CSV path")
    args = p.parse_args(argv)
    env = envs.make("cartpole-swingup-sparse")
    steps = env.episode_length
    keys = jax.random.split(jax.random.key(args.seed), args.episodes)
    rng = np.random.default_rng(args.seed)
    rows = []
    for kind in KINDS:
        rewards, qpos = play(env, keys, random_actions(kind, rng, args.episodes, steps, args.scale))
        rows.append({"kind": kind, "beta": "" if KINDS[kind] is None else KINDS[kind], "scale": args.scale,
                     "episodes": args.episodes, **outcome_columns(rewards, qpos)})
        r = rows[-1]
        print(f"{kind:8s} episodes with reward {r['share_with_reward']:.3f}  mean return {r['mean_return']:7.2f}  "
              f"max {r['max_return']:7.1f}  in region {r['sparse_region_share']:.4f}  turns {r['turns']:.2f}")
    if args.out:
        save_rows(rows, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
