"""MPPI planner: toy optimum, policy prior, warm start, determinism/exploration, pytree latents, jit+vmap, config."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.agents.mppi import MPPIConfig, PlanningModel, estimate_returns, mppi_plan, shift_mean

TARGET = jnp.array([0.6, -0.4])
SCALE = 10.0  # reward scale: makes temperature 0.5 discriminative


def point_model(target=TARGET, policy=None) -> PlanningModel:
    """z' = z + a, r = -SCALE * |z + a - target|^2, zero terminal value; optimum: a_0 = target - z_0 (if reachable)."""
    if policy is None:
        policy = lambda z, key: jax.random.uniform(key, z.shape, minval=-1.0, maxval=1.0)
    return PlanningModel(
        dynamics=lambda z, a: z + a,
        reward=lambda z, a: -SCALE * jnp.sum(jnp.square(z + a - target)),
        value=lambda z, a, key: jnp.zeros(()),
        policy=policy,
    )


def optimal_policy(z, key):
    return jnp.clip(TARGET - z, -1.0, 1.0)


def planner(config, model, explore=False):
    return jax.jit(functools.partial(mppi_plan, config, model, explore=explore))


def plan_over_keys(config, model, z0, n_keys, seed=0):
    """Plan from one state with ``n_keys`` keys (the returned action is a random elite, so judge its distribution)."""
    f = functools.partial(mppi_plan, config, model, explore=False, first_step=True)
    keys = jax.random.split(jax.random.PRNGKey(seed), n_keys)
    return jax.jit(jax.vmap(f, in_axes=(None, None, 0)))(z0, jnp.zeros((config.horizon, 2)), keys)


def test_toy_problem_reaches_analytic_optimum():
    cfg = MPPIConfig()
    a, mean, info = plan_over_keys(cfg, point_model(), jnp.zeros(2), 48)
    assert a.shape == (48, 2) and mean.shape == (48, cfg.horizon, 2) and info["std"].shape == (48, cfg.horizon, 2)
    err = np.abs(np.asarray(a) - np.asarray(TARGET))
    np.testing.assert_allclose(np.asarray(a).mean(axis=0), TARGET, atol=0.03)
    assert np.median(err) < 0.05 and np.quantile(err, 0.9) < 0.12
    np.testing.assert_allclose(np.median(np.asarray(mean[:, 0]), axis=0), TARGET, atol=0.03)
    # After reaching the target the optimal later actions are zero.
    np.testing.assert_allclose(np.median(np.asarray(mean[:, 1:]), axis=0), 0.0, atol=0.05)
    # The std shrinks from max_std towards min_std as the elites agree.
    assert np.median(np.asarray(info["std"][:, 0])) < 0.1


def test_estimate_returns_matches_formula():
    cfg = MPPIConfig(horizon=2, gamma=0.9)
    model = PlanningModel(
        dynamics=lambda z, a: 2.0 * z + a,
        reward=lambda z, a: jnp.sum(z * a),
        value=lambda z, a, key: jnp.sum(z) + jnp.sum(a),
        policy=lambda z, key: jnp.full_like(z, 0.5),
    )
    z0 = jnp.array([1.0])
    actions = jnp.array([[[0.3], [-1.0]], [[0.7], [0.2]]])  # (H=2, N=2, 1)
    got = estimate_returns(cfg, model, z0, actions, jax.random.PRNGKey(0))
    expected = []
    for n in range(2):
        z, g, d = 1.0, 0.0, 1.0
        for t in range(2):
            a = float(actions[t, n, 0])
            g, z, d = g + d * z * a, 2.0 * z + a, d * 0.9
        expected.append(g + d * (z + 0.5))
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    # The value's key is one per estimate (TD-MPC2 draws its Q heads per value call): the same for every
    # sample of an estimate, another for another estimate.
    keyed = model._replace(value=lambda z, a, key: jax.random.uniform(key))
    offsets = [np.asarray(estimate_returns(cfg, keyed, z0, actions, jax.random.PRNGKey(k))) - np.asarray(
        estimate_returns(cfg, model._replace(value=lambda z, a, key: 0.0 * z.sum()), z0, actions,
                         jax.random.PRNGKey(k))) for k in (0, 1)]
    assert np.ptp(offsets[0]) < 1e-6 and np.ptp(offsets[1]) < 1e-6 and abs(offsets[0][0] - offsets[1][0]) > 1e-3


def test_policy_prior_trajectories_drive_the_plan():
    # Tiny std: Gaussian samples cannot leave the (zero) initial mean, only the policy prior knows the optimum.
    cfg = MPPIConfig(min_std=0.005, max_std=0.01)
    z0 = jnp.zeros(2)
    with_prior = planner(cfg, point_model(policy=optimal_policy))
    a, mean, _ = with_prior(z0, jnp.zeros((cfg.horizon, 2)), jax.random.PRNGKey(1), first_step=True)
    np.testing.assert_allclose(a, TARGET, atol=0.02)
    np.testing.assert_allclose(mean[0], TARGET, atol=0.02)
    no_prior = planner(dataclasses.replace(cfg, num_policy_trajectories=0), point_model(policy=optimal_policy))
    a0, _, _ = no_prior(z0, jnp.zeros((cfg.horizon, 2)), jax.random.PRNGKey(1), first_step=True)
    assert np.max(np.abs(np.asarray(a0))) < 0.1  # stuck near the zero mean without the prior


def test_shift_mean():
    prev = jnp.arange(6.0).reshape(3, 2)
    np.testing.assert_array_equal(shift_mean(prev, False), [[2.0, 3.0], [4.0, 5.0], [0.0, 0.0]])
    np.testing.assert_array_equal(shift_mean(prev, jnp.array(True)), np.zeros((3, 2)))
    np.testing.assert_array_equal(jax.jit(shift_mean)(prev, jnp.array(False)), shift_mean(prev, False))


def test_warm_start_is_shifted_into_the_plan():
    # Tiny std and no prior: the plan can only follow the warm-started mean, so the first action is prev_mean[1].
    cfg = MPPIConfig(num_policy_trajectories=0, min_std=0.001, max_std=0.002)
    plan = planner(cfg, point_model())
    prev = jnp.array([[0.9, 0.9], [0.3, -0.2], [0.1, 0.1]])
    key = jax.random.PRNGKey(2)
    a, mean, _ = plan(jnp.zeros(2), prev, key, first_step=jnp.array(False))
    np.testing.assert_allclose(a, prev[1], atol=0.01)
    np.testing.assert_allclose(mean, shift_mean(prev, False), atol=0.01)
    a_first, _, _ = plan(jnp.zeros(2), prev, key, first_step=jnp.array(True))
    np.testing.assert_allclose(a_first, 0.0, atol=0.01)


def test_determinism_and_exploration_noise():
    cfg = MPPIConfig(iterations=3, num_samples=64, num_policy_trajectories=8, num_elites=8)
    model = point_model(target=jnp.zeros(2))
    prev = jnp.zeros((cfg.horizon, 2))
    greedy, noisy = planner(cfg, model, explore=False), planner(cfg, model, explore=True)
    key = jax.random.PRNGKey(3)
    a1, m1, _ = greedy(jnp.zeros(2), prev, key, first_step=True)
    a2, m2, _ = greedy(jnp.zeros(2), prev, key, first_step=True)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(m1, m2)
    a3, _, _ = greedy(jnp.zeros(2), prev, jax.random.PRNGKey(4), first_step=True)
    assert not np.array_equal(a1, a3)  # the elite draw uses the key

    keys = jax.random.split(jax.random.PRNGKey(5), 600)
    batched = lambda f: jax.vmap(lambda k: f(jnp.zeros(2), prev, k, first_step=True))(keys)
    a_greedy, mean_g, info = batched(greedy)
    a_noisy, mean_n, _ = batched(noisy)
    np.testing.assert_array_equal(mean_g, mean_n)  # exploration only perturbs the returned action
    eps = np.asarray((a_noisy - a_greedy) / info["std"][:, 0])
    assert np.all(np.abs(np.asarray(a_noisy)) <= 1.0)
    np.testing.assert_allclose(eps.mean(axis=0), 0.0, atol=0.15)
    np.testing.assert_allclose(eps.std(axis=0), 1.0, atol=0.12)


def test_pytree_latents_match_array_latents():
    cfg = MPPIConfig(iterations=4)
    array_model = point_model()
    dict_model = PlanningModel(
        dynamics=lambda z, a: {"pos": z["pos"] + a, "t": z["t"] + 1.0, "h": jnp.tanh(z["h"])},
        reward=lambda z, a: array_model.reward(z["pos"], a),
        value=lambda z, a, key: jnp.zeros(()) * z["t"],
        policy=lambda z, key: array_model.policy(z["pos"], key),
    )
    z_dict = {"pos": jnp.array([0.2, 0.1]), "t": jnp.zeros(()), "h": jnp.ones((3, 4))}
    prev, key = jnp.zeros((cfg.horizon, 2)), jax.random.PRNGKey(6)
    a_arr, m_arr, _ = planner(cfg, array_model)(z_dict["pos"], prev, key, first_step=True)
    a_dict, m_dict, _ = planner(cfg, dict_model)(z_dict, prev, key, first_step=True)
    np.testing.assert_allclose(a_dict, a_arr, atol=1e-6)
    np.testing.assert_allclose(m_dict, m_arr, atol=1e-6)
    a_many, _, _ = plan_over_keys(cfg, dict_model, z_dict, 16)
    np.testing.assert_allclose(np.asarray(a_many).mean(axis=0), TARGET - z_dict["pos"], atol=0.05)


def test_jit_vmap_over_initial_states():
    cfg = MPPIConfig()
    model = point_model()
    z0 = jnp.array([[0.0, 0.0], [0.3, -0.1], [-0.2, 0.4], [1.0, -1.0]])
    prev = jnp.zeros((len(z0), cfg.horizon, 2))
    keys = jax.random.split(jax.random.PRNGKey(7), len(z0))
    first = jnp.array([True, False, True, False])
    plan = jax.jit(jax.vmap(functools.partial(mppi_plan, cfg, model, explore=True)))
    a, mean, info = plan(z0, prev, keys, first_step=first)
    assert a.shape == (4, 2) and mean.shape == (4, cfg.horizon, 2) and info["std"].shape == (4, cfg.horizon, 2)
    np.testing.assert_allclose(mean[:, 0], np.clip(TARGET - z0, -1.0, 1.0), atol=0.05)
    single = planner(cfg, model, explore=True)
    for i in range(len(z0)):
        a_i, m_i, _ = single(z0[i], prev[i], keys[i], first_step=first[i])
        np.testing.assert_allclose(a[i], a_i, atol=1e-5)
        np.testing.assert_allclose(mean[i], m_i, atol=1e-5)


def test_horizon_one():
    cfg = MPPIConfig(horizon=1, iterations=4)
    a, mean, _ = planner(cfg, point_model())(jnp.zeros(2), jnp.zeros((1, 2)), jax.random.PRNGKey(8), first_step=True)
    np.testing.assert_allclose(mean[0], TARGET, atol=0.05)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"horizon": 0}, "horizon=0"),
        ({"iterations": 2.5}, "iterations=2.5"),
        ({"num_samples": 10, "num_policy_trajectories": 11}, "num_policy_trajectories=11"),
        ({"num_samples": 10, "num_policy_trajectories": 0, "num_elites": 20}, "num_elites=20"),
        ({"num_elites": 0}, "num_elites=0"),
        ({"temperature": -1.0}, "temperature=-1.0"),
        ({"min_std": 0.0}, "min_std=0.0"),
        ({"min_std": 3.0}, "min_std=3.0"),
        ({"gamma": 1.5}, "gamma=1.5"),
        ({"num_policy_trajectories": True}, "num_policy_trajectories=True"),
        ({"explore_min_std": -0.1}, r"explore_min_std=-0.1 is invalid; expected a finite number >= 0"),
        ({"explore_min_std": float("inf")}, "explore_min_std=inf"),
        ({"terminal_q": "median"}, r"terminal_q='median' is invalid; expected one of mean, min"),
    ],
)
def test_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MPPIConfig(**kwargs)


def test_prev_mean_horizon_mismatch():
    with pytest.raises(ValueError, match="horizon"):
        mppi_plan(
            MPPIConfig(),
            point_model(),
            jnp.zeros(2),
            jnp.zeros((5, 2)),
            jax.random.PRNGKey(0),
            explore=False,
            first_step=True,
        )


def test_given_exploration_noise_replaces_the_white_draw():
    cfg = MPPIConfig(iterations=3, num_samples=64, num_policy_trajectories=8, num_elites=8)
    model = point_model(target=jnp.zeros(2))
    prev, key, z0 = jnp.zeros((cfg.horizon, 2)), jax.random.PRNGKey(7), jnp.array([0.2, -0.1])
    greedy, _, info = planner(cfg, model, explore=False)(z0, prev, key, first_step=True)
    noise = jnp.array([0.7, -2.5])  # large enough that the second component clips
    noisy, _, _ = planner(cfg, model, explore=True)(z0, prev, key, first_step=True, explore_noise=noise)
    expected = np.clip(np.asarray(greedy, np.float64) + np.asarray(info["std"][0], np.float64) * [0.7, -2.5], -1, 1)
    np.testing.assert_allclose(noisy, expected, rtol=1e-6, atol=1e-6)
    ignored, _, _ = planner(cfg, model, explore=False)(z0, prev, key, first_step=True, explore_noise=noise)
    np.testing.assert_array_equal(ignored, greedy)  # no exploration, no noise


def test_exploration_noise_floor():
    """``explore_min_std`` scales the noise by max(std[0], floor): a planner whose std collapsed (a sharp optimum:
    std at min_std) still explores at the floor, one whose std is above it is unchanged."""
    cfg = MPPIConfig(iterations=6, num_samples=256, num_policy_trajectories=0, num_elites=16, min_std=0.05)
    model = point_model(target=jnp.zeros(2))
    prev, key, z0 = jnp.zeros((cfg.horizon, 2)), jax.random.PRNGKey(11), jnp.array([0.2, -0.1])
    noise = jnp.array([0.3, -0.6])
    greedy, _, info = planner(cfg, model, explore=False)(z0, prev, key, first_step=True)
    std0 = np.asarray(info["std"][0], np.float64)
    assert np.all(std0 < 0.5)  # the sharp optimum shrank the std below the floor used next
    floored = dataclasses.replace(cfg, explore_min_std=0.5)
    noisy, _, _ = planner(floored, model, explore=True)(z0, prev, key, first_step=True, explore_noise=noise)
    expected = np.clip(np.asarray(greedy, np.float64) + 0.5 * np.asarray(noise, np.float64), -1, 1)
    np.testing.assert_allclose(noisy, expected, rtol=1e-6, atol=1e-6)
    low = dataclasses.replace(cfg, explore_min_std=float(std0.min()) / 2)  # below the std: no change
    plain, _, _ = planner(cfg, model, explore=True)(z0, prev, key, first_step=True, explore_noise=noise)
    same, _, _ = planner(low, model, explore=True)(z0, prev, key, first_step=True, explore_noise=noise)
    np.testing.assert_allclose(same, plain, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(plain, np.clip(np.asarray(greedy, np.float64) + std0 * np.asarray(noise), -1, 1),
                               rtol=1e-6, atol=1e-6)
