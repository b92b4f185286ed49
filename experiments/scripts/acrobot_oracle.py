"""What acrobot-swingup returns a planner reaches that knows the true physics: a ceiling for the learned agents.

    python experiments/scripts/acrobot_oracle.py [--starts dm_control|hanging] [--episodes 10] [--horizon 50]
        [--samples 512] [--iterations 6] [--elites 64] [--temperature 0.5] [--action-repeat 2]
        [--shaping none|height|energy] [--shaping-weight 1] [--chunk 25] [--out CSV]

The learned acrobot agents score least on episodes that start hanging down (``acrobot_hanging_starts.py``); is
issue #5's 700 reachable on dm_control's episodes at all? This plans with the repository's MPPI
(:func:`lnnmpc.agents.mppi.mppi_plan`, deterministic acting, no policy prior) on the MJX simulator itself: the
"latent" is the environment state, the dynamics ``Env.step``, the per-step score the task reward of the state
times the action repeat (plus, with ``--shaping``, ``--shaping-weight`` times a term in [0, 1] that the planner may
use to pump energy where the reward, ~1e-14 hanging down, ranks nothing: the tip's height or how close the
mechanical energy is to the upright's, :func:`planning_model`), and the terminal value the score of the last
state. The returns reported are always the task's own rewards. At the budgets tried (H 30-50, 256-512 samples,
4 iterations; RESULTS.md [79]) it is far weaker than the learned agents, so it is no ceiling yet.

``--starts dm_control`` plays dm_control's seed-0 evaluation starts (episode e from ``task_kwargs={"random": e}``,
the starts of ``lnnmpc.train.cli eval --backend dm_control``), ``--starts hanging`` both links down at rest with
N(0, 0.1^2) noise. Episodes run side by side, ``--chunk`` agent steps per compiled call (a progress line after
each). Per episode: the return, the first agent step with the tip above the shoulder and the start's angles.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np


def dm_control_starts(episodes: int) -> np.ndarray:
    """dm_control's acrobot-swingup initial joint angles (episodes, 2) for ``task_kwargs={"random": e}``."""
    from dm_control import suite

    starts = []
    for e in range(episodes):
        env = suite.load("acrobot", "swingup", task_kwargs={"random": e})
        env.reset()
        starts.append(np.array(env.physics.data.qpos, np.float64))
    return np.stack(starts)


def hanging_starts(episodes: int, sigma: float, key: jax.Array) -> np.ndarray:
    """Both links down at rest plus N(0, sigma^2) noise on each angle (episodes, 2), wrapped to [-pi, pi)."""
    qpos = np.array([np.pi, 0.0]) + sigma * np.asarray(jax.random.normal(key, (episodes, 2)))
    return np.mod(qpos + np.pi, 2 * np.pi) - np.pi


def mechanical_energy(env, data) -> jax.Array:
    """Kinetic plus potential energy of the acrobot's MJX state (J): 0.5 qvel' M qvel + sum_i m_i g z_i (the
    bodies' centres of mass)."""
    from mujoco import mjx

    kinetic = 0.5 * jnp.dot(data.qvel, mjx.mul_m(env.mjx_model, data, data.qvel))
    potential = -jnp.sum(env.mjx_model.body_mass * data.xipos[:, 2]) * env.mj_model.opt.gravity[2]
    return kinetic + potential


def state_energy(env):
    """A jitted ``energy(qpos, qvel)``: :func:`mechanical_energy` of the state ``env.reset_to`` puts the acrobot in
    (one compiled program; MJX's forward pass run op by op costs ~30 s of small compilations on a CPU)."""
    return jax.jit(lambda qpos, qvel: mechanical_energy(env, env.reset_to(qpos, qvel).physics))


def energy_range(env) -> tuple[float, float]:
    """The energies at rest hanging down (shoulder pi) and balanced upright (all angles 0)."""
    energy = state_energy(env)
    return float(energy(jnp.array([jnp.pi, 0.0]), jnp.zeros(2))), float(energy(jnp.zeros(2), jnp.zeros(2)))


def planning_model(env, shaping: str, weight: float):
    """:class:`PlanningModel` over environment states: the true step, the state's reward (+ ``weight`` times a
    shaping term in [0, 1]: the tip's height above its lowest point / 4 (``height``), or 1 - |E - E_up| /
    (E_up - E_down) for the mechanical energy E (``energy``, Spong's swing-up target))."""
    from lnnmpc.agents.mppi import PlanningModel

    repeat = float(env.action_repeat)
    down, up = energy_range(env)

    def score(state, action):
        data = state.physics
        reward = env.spec.reward(data, action, env.ids)
        if shaping == "height":
            lowest = data.xpos[env.ids["arms"][0]][2] - 2.0  # the shoulder's height minus both links
            reward = reward + weight * (data.site_xpos[env.ids["tip"]][2] - lowest) / 4.0
        elif shaping == "energy":
            reward = reward + weight * (1.0 - jnp.abs(mechanical_energy(env, data) - up) / (up - down))
        return repeat * reward

    return PlanningModel(
        dynamics=env.step,
        reward=score,
        value=lambda state, action, key: score(state, action),
        policy=lambda state, key: jnp.zeros((env.action_size,)),
    )


def make_advance(env, config, model, chunk: int):
    """A jitted ``advance(carry) -> (carry, (rewards, tip heights) (chunk, episodes))`` over episodes side by side."""
    from lnnmpc.agents.mppi import mppi_plan

    def one_step(carry, _):
        state, mean, key = carry
        key, k_plan = jax.random.split(key)
        action, mean, _ = mppi_plan(config, model, state, mean, k_plan, explore=False, first_step=state.t == 0)
        state = env.step(state, action)
        tip_above = state.physics.site_xpos[env.ids["tip"]][2] - state.physics.xpos[env.ids["arms"][0]][2]
        return (state, mean, key), (state.reward, tip_above)

    def advance(carry):
        return jax.lax.scan(jax.vmap(one_step), carry, None, length=chunk)

    return jax.jit(advance)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--starts", default="dm_control", choices=("dm_control", "hanging"))
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--horizon", type=int, default=50)
    p.add_argument("--samples", type=int, default=512)
    p.add_argument("--iterations", type=int, default=6)
    p.add_argument("--elites", type=int, default=64)
    p.add_argument("--temperature", type=float, default=0.5)
    p.add_argument("--action-repeat", type=int, default=2)
    p.add_argument("--shaping", default="none", choices=("none", "height", "energy"))
    p.add_argument("--shaping-weight", type=float, default=1.0)
    p.add_argument("--chunk", type=int, default=25)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    from lnnmpc.agents.mppi import MPPIConfig
    from lnnmpc.envs.env import make
    from lnnmpc.train import runfolder

    try:
        if args.episodes < 1 or args.chunk < 1 or args.shaping_weight < 0:
            raise ValueError(f"--episodes and --chunk must be >= 1 and --shaping-weight >= 0, got {args.episodes}, "
                             f"{args.chunk} and {args.shaping_weight}")
        env = make("acrobot-swingup", action_repeat=args.action_repeat)
        config = MPPIConfig(horizon=args.horizon, iterations=args.iterations, num_samples=args.samples,
                            num_policy_trajectories=0, num_elites=args.elites, temperature=args.temperature)
    except ValueError as error:
        print(error, file=sys.stderr)
        return 2
    starts = (dm_control_starts(args.episodes) if args.starts == "dm_control"
              else hanging_starts(args.episodes, 0.1, jax.random.key(0)))
    states = jax.vmap(lambda q: env.reset_to(q, jnp.zeros(2)))(jnp.asarray(starts, jnp.float32))
    means = jnp.zeros((args.episodes, args.horizon, env.action_size))
    carry = (states, means, jax.random.split(jax.random.key(1), args.episodes))
    advance = make_advance(env, config, planning_model(env, args.shaping, args.shaping_weight), args.chunk)
    rewards, heights, began = [], [], time.time()
    while sum(len(r) for r in rewards) < env.episode_length:
        carry, (r, h) = advance(carry)
        rewards.append(np.asarray(r)), heights.append(np.asarray(h))
        done = sum(len(r) for r in rewards)
        print(f"  {done}/{env.episode_length} agent steps, {time.time() - began:.0f} s, returns so far "
              f"{np.concatenate(rewards).sum(axis=0).round(0).tolist()}", flush=True)
    ret = np.concatenate(rewards)[: env.episode_length].sum(axis=0)
    above = np.concatenate(heights)[: env.episode_length] > 0  # (T, E)
    first = np.where(above.any(axis=0), above.argmax(axis=0), -1)
    setting = (f"H={args.horizon} samples={args.samples} iterations={args.iterations} elites={args.elites} "
               f"temperature={args.temperature} repeat={args.action_repeat} "
               f"shaping={args.shaping}x{args.shaping_weight}")
    print(f"oracle MPPI ({setting}), {args.starts} starts: return {ret.mean():.1f} +- {ret.std():.1f} (episodes "
          f"{' '.join(f'{x:.0f}' for x in ret)}); tip first above the shoulder at agent steps "
          f"{' '.join(str(int(f)) for f in first)}; {time.time() - began:.0f} s")
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        rows = [{"starts": args.starts, "setting": setting, "episode": e, "return": float(ret[e]),
                 "first_step_above": int(first[e]), "start_shoulder": float(starts[e, 0]),
                 "start_elbow": float(starts[e, 1])} for e in range(args.episodes)]
        runfolder.write_csv(args.out, list(rows[0]), rows)
        print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
