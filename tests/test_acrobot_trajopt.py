"""``lnnmpc.analysis.acrobot_trajopt``: iLQR against the finite-horizon Riccati recursion (float64 numpy) on a linear
quadratic problem, its control limits, and its optimised acrobot trajectory replayed in dm_control."""

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.analysis import acrobot_trajopt as at

A = np.array([[1.0, 0.1], [0.0, 1.0]])
B = np.array([0.0, 0.1])
Q, R, T = np.eye(2), 0.1, 20


def _lq_problem():
    return at.Problem(dynamics=lambda x, u: jnp.asarray(A) @ x + jnp.asarray(B) * u,
                      cost=lambda x, u: x @ jnp.asarray(Q) @ x + R * u ** 2)


def _riccati(x0):
    """Finite-horizon LQR in float64 numpy: no terminal cost, gains K_t (u_t = K_t x_t) and the optimal controls."""
    p, gains = np.zeros((2, 2)), []
    for _ in range(T):
        k = -np.linalg.solve(np.array([[R + B @ p @ B]]), (B @ p @ A)[None])[0]
        p = Q + A.T @ p @ A + np.outer(A.T @ p @ B, k)
        gains.append(k)
    gains = gains[::-1]
    x, us = np.asarray(x0, float), []
    for k in gains:
        us.append(k @ x)
        x = A @ x + B * us[-1]
    return np.array(gains), np.array(us)


def _cost(us, x0):
    x, total = np.asarray(x0, float), 0.0
    for u in us:
        total += x @ Q @ x + R * u ** 2
        x = A @ x + B * u
    return total


def test_ilqr_solves_a_linear_quadratic_problem_as_riccati_does():
    x0 = np.array([0.5, -0.2])  # small enough that no control reaches the limits
    with jax.enable_x64(True):
        us, xs, gains, costs = at.ilqr(_lq_problem(), jnp.asarray(x0), jnp.zeros(T), iterations=4, mu=1e-9)
    want_gains, want_us = _riccati(x0)
    assert np.abs(want_us).max() < 1.0
    np.testing.assert_allclose(np.asarray(us), want_us, atol=1e-7)
    np.testing.assert_allclose(np.asarray(gains), want_gains, atol=1e-5)  # regularised by mu >= 1e-6
    np.testing.assert_allclose(np.asarray(costs)[-1], _cost(want_us, x0), rtol=1e-9)
    assert np.all(np.diff(np.asarray(costs)) <= 1e-12)  # only improving steps are kept
    np.testing.assert_allclose(np.asarray(xs)[-1], A @ np.asarray(xs)[-2] + B * want_us[-1], atol=1e-9)
    with jax.enable_x64(True):  # around given states (the initial controls' own rollout): the same solution
        start = jnp.full(T, 0.3)
        given, cost = at.rollout(_lq_problem(), jnp.asarray(x0), start)
        np.testing.assert_allclose(float(at.trajectory_cost(_lq_problem(), given, start)), float(cost), rtol=1e-12)
        again = at.ilqr(_lq_problem(), jnp.asarray(x0), start, iterations=4, mu=1e-9, xs=given)[0]
    np.testing.assert_allclose(np.asarray(again), want_us, atol=1e-7)


def test_ilqr_keeps_controls_in_their_limits_and_beats_the_clipped_riccati_policy():
    x0 = np.array([6.0, -3.0])  # the unconstrained optimum asks for |u| > 1
    want_gains, want_us = _riccati(x0)
    assert np.abs(want_us).max() > 1.0
    with jax.enable_x64(True):
        us, _, _, costs = at.ilqr(_lq_problem(), jnp.asarray(x0), jnp.zeros(T), iterations=30, mu=1e-6)
    us = np.asarray(us)
    assert np.abs(us).max() <= 1.0 and np.isclose(np.abs(us).max(), 1.0)
    x, clipped = x0.copy(), []  # a feasible policy: Riccati's gains, clipped
    for k in want_gains:
        clipped.append(np.clip(k @ x, -1, 1))
        x = A @ x + B * clipped[-1]
    assert float(np.asarray(costs)[-1]) < _cost(np.array(clipped), x0)
    np.testing.assert_allclose(float(np.asarray(costs)[-1]), _cost(us, x0), rtol=1e-9)


def test_closed_form_returns_and_states_are_dm_controls():
    """Random smooth actions for the first 60 agent steps of dm_control's starts 3 and 4: the closed form's states
    and return (acrobot_problem's reward summed over both control steps of each agent step, from each stored
    state) are the ones dm_control's play gives, with no feedback needed over this stretch."""
    config = at.TrajoptConfig(restarts=2)
    envs = at.ceiling.dm_control_envs([3, 4])
    p = at.physics.params_from_model(envs[0].physics.model.ptr)
    starts = np.stack([np.concatenate([env.physics.data.qpos, env.physics.data.qvel]) for env in envs])
    with jax.enable_x64(True):
        us = np.asarray(at.initial_controls(jax.random.PRNGKey(0), config, 2, 60))
        assert us.shape == (2, 2, 60) and np.all(us[:, 0] == 0) and np.abs(us).max() <= 1 and us[:, 1].std() > 0.1
        us = us[:, 1]
        xs = at.rollouts(p, 2, jnp.asarray(starts), jnp.asarray(us))
        assert xs.shape == (2, 61, 4) and np.array_equal(xs[:, 0], starts)
        returns = at.trajectory_returns(p, 2, jnp.asarray(xs), jnp.asarray(us))
    rows = at.play_in_dm_control(envs, config, us, xs, np.zeros((2, 60, 4)))
    assert all(row["max_state_deviation"] < 1e-9 for row in rows)
    np.testing.assert_allclose([row["return"] for row in rows], returns, rtol=1e-9)
    assert returns[0] > 1e-3 and returns[1] < 1e-6  # start 3 begins with the tip above the shoulder, 4 hangs


def test_cli_refuses_bad_values_naming_them(capsys):
    assert at.main(["--action-repeat", "3"]) == 2
    assert "action_repeat must divide the episode's 1000 control steps, got 3" in capsys.readouterr().err
    assert at.main(["--mu", "0"]) == 2
    assert "mu > 0" in capsys.readouterr().err
    assert at.main(["--episodes", "0"]) == 2
    assert "--episodes must be >= 1" in capsys.readouterr().err
