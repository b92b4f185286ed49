"""``python -m lnnmpc.analysis.acrobot_trajopt``: the best return found for each acrobot-swingup start by optimising
the whole episode's actions on the exact dynamics, then played in dm_control.

    python -m lnnmpc.analysis.acrobot_trajopt [--episodes 10] [--first-episode 0] [--restarts 8]
        [--iterations 150] [--action-repeat 2] [--out CSV]

RESULTS.md [81] bounded acrobot-swingup from below with receding-horizon MPPI (2 s ahead) on the exact equations of
motion: 559.2 on dm_control's evaluation starts 0-9, while a learned policy scored 879 from a start where that
planner got 713. A planner that looks 2 s ahead cannot see when a slower swing now pays later. This module looks
at the whole episode instead: iterative LQR (iLQR, control-limited, Levenberg-Marquardt regularised) over all
``1000 / action_repeat`` agent steps from the start, maximising the sum of dm_control's rewards (the tip's
``tolerance``) computed on :mod:`lnnmpc.analysis.acrobot_physics`'s closed-form dynamics in float64. The reward is
~1e-14 with the chain hanging down, so the first stages add the planner's energy and tip-height shaping and later
stages anneal it to zero (:data:`STAGES`); ``--restarts`` random smooth initial action sequences per start (the
first all zeros), the best kept by the true return. The solution is then played in dm_control itself as a policy:
the optimised action plus iLQR's time-varying feedback gain times the state's deviation from the optimised
trajectory, so MuJoCo's small differences from the closed form do not grow. Every return reported is dm_control's.

A higher return here is another lower bound on the best possible, one that no learned agent with that action
repeat can be expected to beat on average (it knows the start's exact state and the dynamics, and it may take
seconds of CPU per start); the returns under the closed form are reported beside the played ones.
"""

from __future__ import annotations

import csv
import functools
import sys
import time
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from lnnmpc.analysis import acrobot_ceiling as ceiling
from lnnmpc.analysis import acrobot_physics as physics
from lnnmpc.analysis.acrobot_ceiling import PlannerConfig
from lnnmpc.analysis.acrobot_physics import EPISODE_STEPS, AcrobotParams

# (energy_weight, height_weight) of each stage, run one after the other for ``iterations`` iLQR iterations each:
# shaping pumps energy where the reward ranks nothing, the last stages optimise dm_control's reward alone.
STAGES = ((0.1, 0.1), (0.03, 0.03), (0.01, 0.0), (0.0, 0.0))


class TrajoptConfig(NamedTuple):
    """iLQR over ``EPISODE_STEPS // action_repeat`` agent steps: ``iterations`` per stage of :data:`STAGES`,
    ``restarts`` initial action sequences (smooth noise of std ``init_std`` at knots every ``knot`` agent steps,
    the first all zeros), ``control_cost`` times u^2 added per agent step, the regulariser starting at ``mu``."""

    action_repeat: int = 2
    iterations: int = 150
    restarts: int = 8
    init_std: float = 0.7
    knot: int = 10
    control_cost: float = 1e-4
    mu: float = 1.0

    def validate(self) -> None:
        """Raises ValueError naming the first impossible value."""
        for name in ("action_repeat", "iterations", "restarts", "knot"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if EPISODE_STEPS % self.action_repeat:
            raise ValueError(f"action_repeat must divide the episode's {EPISODE_STEPS} control steps, got "
                             f"{self.action_repeat}")
        if self.init_std < 0 or self.control_cost < 0 or self.mu <= 0:
            raise ValueError(f"need init_std >= 0, control_cost >= 0 and mu > 0, got {self.init_std}, "
                             f"{self.control_cost} and {self.mu}")


class Problem(NamedTuple):
    """An iLQR problem: ``dynamics(x, u) -> x'`` and ``cost(x, u) -> scalar`` of one state ``(n,)`` and a scalar
    control in [-1, 1]; no terminal cost."""

    dynamics: object
    cost: object


def acrobot_problem(p: AcrobotParams, repeat: int, energy_weight: float, height_weight: float,
                    control_cost: float) -> tuple[Problem, object]:
    """The acrobot's agent step (``repeat`` RK4 control steps, the action held) on states ``(4,)`` = (shoulder,
    elbow, their velocities), with the cost minus the summed reward and shaping of :mod:`acrobot_ceiling`'s
    planner. Also returns ``reward(x, u)``: dm_control's reward summed over the agent step."""
    import jax
    import jax.numpy as jnp

    def substeps(x, u):
        def control_step(state, _):
            q, v = physics.rk4_step(p, state[:2], state[2:], u)
            nxt = jnp.concatenate([q, v])
            closeness, height = ceiling.shaping_terms(p, q, v)
            return nxt, (physics.tip_reward(p, q), closeness, height)

        return jax.lax.scan(control_step, x, None, length=repeat)

    def dynamics(x, u):
        return substeps(x, u)[0]

    def cost(x, u):
        _, (reward, closeness, height) = substeps(x, u)
        shaped = reward + energy_weight * closeness + height_weight * height
        return control_cost * u ** 2 - shaped.sum()

    def reward(x, u):
        return substeps(x, u)[1][0].sum()

    return Problem(dynamics, cost), reward


def rollout(problem: Problem, x0, us):
    """States ``(T + 1, n)`` and total cost of controls ``(T,)`` from ``x0`` ``(n,)``."""
    import jax
    import jax.numpy as jnp

    def step(x, u):
        return problem.dynamics(x, u), (x, problem.cost(x, u))

    last, (xs, costs) = jax.lax.scan(step, x0, us)
    return jnp.concatenate([xs, last[None]]), costs.sum()


def backward_pass(problem: Problem, xs, us, mu):
    """One iLQR backward pass around the trajectory ``xs`` ``(T + 1, n)``, ``us`` ``(T,)``: the dynamics linearised,
    the cost expanded to second order, the value's Hessian regularised by ``mu`` (Tassa et al.), the scalar control
    clamped to [-1, 1] (a clamped step gets no feedback). Returns the feedforward ``k`` ``(T,)``, the gains ``K``
    ``(T, n)`` and whether every ``Q_uu`` was positive."""
    import jax
    import jax.numpy as jnp

    n = xs.shape[1]
    fx, fu = jax.vmap(jax.jacfwd(problem.dynamics, argnums=(0, 1)))(xs[:-1], us)
    grads = jax.vmap(jax.grad(problem.cost, argnums=(0, 1)))(xs[:-1], us)
    hess = jax.vmap(jax.hessian(problem.cost, argnums=(0, 1)))(xs[:-1], us)
    lx, lu = grads
    (lxx, lxu), (lux, luu) = hess

    def step(carry, inputs):
        vx, vxx, ok = carry
        fx_t, fu_t, lx_t, lu_t, lxx_t, lxu_t, luu_t, u_t = inputs
        reg = vxx + mu * jnp.eye(n)
        qx = lx_t + fx_t.T @ vx
        qu = lu_t + fu_t @ vx
        qxx = lxx_t + fx_t.T @ vxx @ fx_t
        quu = luu_t + fu_t @ reg @ fu_t
        qux = lxu_t + fx_t.T @ reg @ fu_t  # (n,)
        ok = ok & (quu > 0)
        safe = jnp.where(quu > 0, quu, 1.0)
        raw = -qu / safe
        k = jnp.clip(u_t + raw, -1.0, 1.0) - u_t
        gain = jnp.where(jnp.abs(u_t + raw) < 1.0, -qux / safe, jnp.zeros(n))
        quu_plain = luu_t + fu_t @ vxx @ fu_t
        qux_plain = lxu_t + fx_t.T @ vxx @ fu_t
        vx = qx + gain * quu_plain * k + gain * qu + qux_plain * k
        vxx = qxx + quu_plain * jnp.outer(gain, gain) + jnp.outer(gain, qux_plain) + jnp.outer(qux_plain, gain)
        vxx = 0.5 * (vxx + vxx.T)
        return (vx, vxx, ok), (k, gain)

    carry = (jnp.zeros(n, xs.dtype), jnp.zeros((n, n), xs.dtype), jnp.array(True))
    (_, _, ok), (k, gains) = jax.lax.scan(step, carry, (fx, fu, lx, lu, lxx, lxu, luu, us), reverse=True)
    return k, gains, ok


def forward_pass(problem: Problem, xs, us, k, gains, alpha):
    """The new controls ``(T,)``, states and total cost of the policy ``u = clip(us + alpha k + K (x - xs))``."""
    import jax
    import jax.numpy as jnp

    def step(x, inputs):
        x_ref, u_ref, k_t, gain = inputs
        u = jnp.clip(u_ref + alpha * k_t + gain @ (x - x_ref), -1.0, 1.0)
        return problem.dynamics(x, u), (x, u, problem.cost(x, u))

    last, (new_xs, new_us, costs) = jax.lax.scan(step, xs[0], (xs[:-1], us, k, gains))
    return new_us, jnp.concatenate([new_xs, last[None]]), costs.sum()


ALPHAS = 0.5 ** np.arange(10)


def trajectory_cost(problem: Problem, xs, us):
    """Total cost of a trajectory's stored states ``(T + 1, n)`` and controls ``(T,)``, each stage's cost from
    its own state (no re-simulation, so round-off cannot grow through a chaotic swing)."""
    import jax

    return jax.vmap(problem.cost)(xs[:-1], us).sum()


def ilqr(problem: Problem, x0, us, iterations: int, mu: float = 1.0, xs=None):
    """``iterations`` of control-limited iLQR from controls ``us`` ``(T,)`` in [-1, 1] (around the states ``xs``
    ``(T + 1, n)`` they came with, if given; else around their rollout from ``x0``): each iteration tries the step
    sizes :data:`ALPHAS` side by side and keeps the lowest cost if it is lower (then ``mu`` shrinks by 3, else it
    grows by 4, within [1e-6, 1e10]). Returns the controls, states ``(T + 1, n)``, the feedback gains ``(T, n)``
    of a backward pass around them (``mu`` at most its start) and the cost after each iteration
    ``(iterations,)``."""
    import jax
    import jax.numpy as jnp

    if xs is None:
        xs, cost = rollout(problem, x0, us)
    else:
        cost = trajectory_cost(problem, xs, us)

    def iteration(carry, _):
        xs, us, cost, mu = carry
        k, gains, ok = backward_pass(problem, xs, us, mu)
        tried_us, tried_xs, tried = jax.vmap(lambda a: forward_pass(problem, xs, us, k, gains, a))(
            jnp.asarray(ALPHAS, xs.dtype))
        best = jnp.argmin(tried)
        better = ok & (tried[best] < cost)
        keep = lambda new, old: jnp.where(better, new, old)
        carry = (keep(tried_xs[best], xs), keep(tried_us[best], us), keep(tried[best], cost),
                 jnp.clip(jnp.where(better, mu / 3.0, mu * 4.0), 1e-6, 1e10))
        return carry, carry[2]

    start = (xs, us, cost, jnp.asarray(mu, xs.dtype))
    (xs, us, _, last_mu), costs = jax.lax.scan(iteration, start, None, length=iterations)
    _, gains, _ = backward_pass(problem, xs, us, jnp.minimum(last_mu, mu))
    return us, xs, gains, costs


def initial_controls(key, config: TrajoptConfig, batch: int, steps: int):
    """``(batch, restarts, steps)`` initial action sequences: restart 0 all zeros, the others smooth noise of std
    ``init_std`` (normal at knots every ``knot`` steps, linearly interpolated), clipped to [-1, 1]."""
    import jax
    import jax.numpy as jnp

    knots = ceiling.knot_count(steps, config.knot)
    at_knots = config.init_std * jax.random.normal(key, (batch, config.restarts, knots), jnp.float64)
    noise = ceiling.interpolate_knots(at_knots, steps, config.knot)
    return jnp.clip(noise.at[:, 0].set(0.0), -1.0, 1.0)


def mppi_controls(p: AcrobotParams, planner: PlannerConfig, starts, seed: int = 0):
    """The actions ``(B, T)`` (``T = EPISODE_STEPS // action_repeat``) that :mod:`acrobot_ceiling`'s
    receding-horizon planner takes from each start ``(B, 4)``, and the states ``(B, T + 1, 4)`` they lead to, when
    its acting is simulated on the closed form (float64) instead of in dm_control (MuJoCo agrees to round-off a
    step, which a chaotic swing can grow over an episode), planning in float64 where [81] planned in float32 and
    acted in dm_control."""
    import jax
    import jax.numpy as jnp

    steps = EPISODE_STEPS // planner.action_repeat

    def episode(x0, key):
        def agent_step(carry, key):
            x, mean = carry
            u, mean = ceiling.plan_and_shift(p, planner, x[:2], x[2:], mean, key)
            for _ in range(planner.action_repeat):
                q, v = physics.rk4_step(p, x[:2], x[2:], u)
                x = jnp.concatenate([q, v])
            return (x, mean), (u, x)

        start = (x0, jnp.zeros(planner.horizon, x0.dtype))
        us, xs = jax.lax.scan(agent_step, start, jax.random.split(key, steps))[1]
        return us, jnp.concatenate([x0[None], xs])

    keys = jax.random.split(jax.random.PRNGKey(seed), len(starts))
    return jax.jit(jax.vmap(episode))(jnp.asarray(starts, jnp.float64), keys)


def trajectory_returns(p: AcrobotParams, repeat: int, xs, us):
    """dm_control's return ``(...)`` of trajectories' stored states ``(..., T + 1, 4)`` and controls ``(..., T)``
    under the closed form: each agent step's rewards (summed over its control steps) from its own state."""
    flat = _returns_program(p, repeat)(xs.reshape(-1, *xs.shape[-2:]), us.reshape(-1, us.shape[-1]))
    return np.asarray(flat).reshape(us.shape[:-1])


@functools.lru_cache(maxsize=8)
def _returns_program(p: AcrobotParams, repeat: int):
    """:func:`trajectory_returns`' jitted program over a batch, built once per chain and action repeat (it is
    called after every stage)."""
    import jax

    _, reward = acrobot_problem(p, repeat, 0.0, 0.0, 0.0)
    return jax.jit(jax.vmap(lambda xs, us: jax.vmap(reward)(xs[:-1], us).sum()))


def rollouts(p: AcrobotParams, repeat: int, starts, us):
    """States ``(..., T + 1, 4)`` of action sequences ``(..., T)`` from their starts ``(..., 4)``."""
    import jax

    problem, _ = acrobot_problem(p, repeat, 0.0, 0.0, 0.0)
    flat = jax.jit(jax.vmap(lambda x0, u: rollout(problem, x0, u)[0]))(
        starts.reshape(-1, 4), us.reshape(-1, us.shape[-1]))
    return np.asarray(flat).reshape(*us.shape[:-1], us.shape[-1] + 1, 4)


def optimise_episodes(p: AcrobotParams, config: TrajoptConfig, xs, us, stages=STAGES, progress: bool = True):
    """Runs ``config.iterations`` iLQR iterations per stage of ``stages`` (``(energy_weight, height_weight)``
    pairs, one after the other) from every initial trajectory, states ``xs`` ``(B, R, T + 1, 4)`` (each starting
    at its start) and controls ``us`` ``(B, R, T)``, and keeps per start the trajectory of the highest closed-form
    return (:func:`trajectory_returns`). Returns controls ``(B, T)``, states ``(B, T + 1, 4)``, feedback gains
    ``(B, T, 4)``, and every trajectory's closed-form return ``(B, R)``."""
    import jax
    import jax.numpy as jnp

    xs, us = jnp.asarray(xs, jnp.float64), jnp.asarray(us, jnp.float64)
    b = us.shape[0]

    def solve_one(weights, x, u):
        problem, _ = acrobot_problem(p, config.action_repeat, weights[0], weights[1], config.control_cost)
        return ilqr(problem, x[0], u, config.iterations, config.mu, xs=x)

    solve = jax.jit(jax.vmap(jax.vmap(solve_one, in_axes=(None, 0, 0)), in_axes=(None, 0, 0)))
    began = time.time()
    for number, weights in enumerate(stages):
        us, xs, gains, _ = solve(jnp.asarray(weights, jnp.float64), xs, us)
        if progress:
            got = trajectory_returns(p, config.action_repeat, xs, us)
            print(f"  stage {number + 1}/{len(stages)} (energy, height weights {weights}): best closed-form "
                  f"returns {np.round(got.max(axis=1), 1).tolist()} ({time.time() - began:.0f} s)",
                  file=sys.stderr, flush=True)
    every = trajectory_returns(p, config.action_repeat, xs, us)
    pick = np.argmax(every, axis=1)
    take = lambda a: np.asarray(a)[np.arange(b), pick]
    return take(us), take(xs), take(gains), every


def play_in_dm_control(envs, config: TrajoptConfig, us, xs, gains) -> list[dict]:
    """Plays each (reset) environment with ``u = clip(us[t] + gains[t] (x - xs[t]))`` every agent step (``x`` the
    physics' own state), the action held ``action_repeat`` control steps. Returns per episode dm_control's return,
    the control steps with the reward above 0.9 and the largest state deviation from the optimised trajectory."""
    rows = []
    for i, env in enumerate(envs):
        total, near, deviation = 0.0, 0, 0.0
        for t in range(us.shape[1]):
            x = np.concatenate([env.physics.data.qpos, env.physics.data.qvel])
            deviation = max(deviation, float(np.abs(x - xs[i, t]).max()))
            u = float(np.clip(us[i, t] + gains[i, t] @ (x - xs[i, t]), -1.0, 1.0))
            for _ in range(config.action_repeat):
                reward = env.step(np.array([u])).reward
                total += reward
                near += reward > 0.9
        rows.append({"return": total, "control_steps_reward_above_0.9": near, "max_state_deviation": deviation})
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    defaults = TrajoptConfig()
    parser = ceiling.episode_parser(__doc__.split("\n")[0], defaults, episodes=2)
    parser.add_argument("--init", choices=("noise", "mppi"), default="noise",
                        help="noise: --restarts smooth random sequences through every stage of STAGES; mppi: the "
                             "receding-horizon planner's actions (acrobot_ceiling's defaults), then the last stage")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="acrobot_trajopt.csv")
    args = parser.parse_args(argv)
    config = ceiling.checked_config("acrobot_trajopt", defaults, args)
    if config is None:
        return 2
    import jax

    jax.config.update("jax_enable_x64", True)
    episodes = list(range(args.first_episode, args.first_episode + args.episodes))
    envs = ceiling.dm_control_envs(episodes)
    p = physics.params_from_model(envs[0].physics.model.ptr)
    starts = np.stack([np.concatenate([env.physics.data.qpos, env.physics.data.qvel]) for env in envs])
    steps = EPISODE_STEPS // config.action_repeat
    began = time.time()
    if args.init == "mppi":  # the planner's own trajectories (its states as it acted)
        config = config._replace(restarts=1)
        us, xs = mppi_controls(p, PlannerConfig(action_repeat=config.action_repeat), starts, args.seed)
        us, xs = np.asarray(us)[:, None], np.asarray(xs)[:, None]
        stages = STAGES[-1:]
    else:
        us = np.asarray(initial_controls(jax.random.PRNGKey(args.seed), config, len(episodes), steps))
        xs = rollouts(p, config.action_repeat, starts[:, None].repeat(config.restarts, 1), us)
        stages = STAGES
    initial = trajectory_returns(p, config.action_repeat, xs, us)
    best_us, best_xs, gains, every = optimise_episodes(p, config, xs, us, stages)
    rows = play_in_dm_control(envs, config, best_us, best_xs, gains)  # still at their starts
    seconds = time.time() - began
    fields = ["episode", "init", "start_shoulder", "start_elbow", "initial_closed_form_return",
              "closed_form_return", "return", "control_steps_reward_above_0.9", "max_state_deviation",
              *defaults._fields, "seed", "seconds"]
    with open(args.out, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        for i, (episode, row) in enumerate(zip(episodes, rows, strict=True)):
            writer.writerow({"episode": episode, "init": args.init, "start_shoulder": starts[i, 0],
                             "start_elbow": starts[i, 1], "initial_closed_form_return": initial[i].max(),
                             "closed_form_return": every[i].max(), **row, **config._asdict(), "seed": args.seed,
                             "seconds": round(seconds, 1)})
    print("| episode | init's best closed-form return | optimised (closed form) | dm_control return |")
    print("|---|---:|---:|---:|")
    for i, (episode, row) in enumerate(zip(episodes, rows, strict=True)):
        print(f"| {episode} | {initial[i].max():.1f} | {every[i].max():.1f} | {row['return']:.1f} |")
    returns = np.array([row["return"] for row in rows])
    print(f"\nmean {returns.mean():.1f} over {len(rows)} episodes ({seconds:.0f} s); rows in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
