"""Observation corruptions (SPEC §3): statistics, ordering, reproducibility, jit and vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc import envs
from lnnmpc.envs.corruptions import CorruptionConfig, corruption_reset, corruption_step, kept_indices

OBS_DIM = 6


def _stream(config: CorruptionConfig, clean: jax.Array, key: jax.Array):
    """Runs the corruption pipeline over a clean stream (T, obs_dim) -> obs (T, d), dt (T,), tau (T,), state."""
    k0, k_steps = jax.random.split(key)
    state, obs0, dt0 = corruption_reset(config, k0, clean[0])

    def body(state, inputs):
        t, obs, k = inputs
        state, delivered, dt = corruption_step(config, state, k, t, obs)
        return state, (delivered, dt, state.tau)

    steps = jnp.arange(1, clean.shape[0], dtype=jnp.int32)
    keys = jax.random.split(k_steps, clean.shape[0] - 1)
    final, (obs, dt, tau) = jax.lax.scan(body, state, (steps, clean[1:], keys))
    return (
        jnp.concatenate([obs0[None], obs]),
        jnp.concatenate([dt0[None], dt]),
        jnp.concatenate([jnp.zeros((1,), jnp.int32), tau]),
        final,
    )


def _clean(T: int = 400) -> jax.Array:
    """A deterministic clean stream whose rows are all distinct and nonzero: row t = t + 1 + dim / 10."""
    return (jnp.arange(T)[:, None] + 1.0 + jnp.arange(OBS_DIM)[None, :] / 10).astype(jnp.float32)


def test_noise_has_requested_standard_deviation():
    sigma = 0.3
    config = CorruptionConfig(obs_noise=sigma)
    clean = _clean(2000)
    obs, dt, _, _ = jax.jit(lambda k: _stream(config, clean, k))(jax.random.key(0))
    residual = np.asarray(obs - clean)
    np.testing.assert_allclose(residual.std(axis=0), sigma, rtol=0.08)
    np.testing.assert_allclose(residual.mean(axis=0), 0.0, atol=4 * sigma / np.sqrt(2000))
    np.testing.assert_array_equal(np.asarray(dt), 1.0)


def test_flicker_drops_each_dimension_at_its_own_rate():
    config = CorruptionConfig(flicker=0.4)
    clean = _clean(3000)
    run = jax.jit(jax.vmap(lambda k: _stream(config, clean, k)))
    obs, _, _, final = run(jax.random.split(jax.random.key(1), 4))
    p = np.asarray(final.flicker_p)  # (4, obs_dim), drawn once per episode
    assert p.shape == (4, OBS_DIM) and np.all((p >= 0) & (p <= 1))
    assert np.std(p) > 0.05  # rates differ across dimensions and episodes
    dropped = np.asarray(obs == 0).mean(axis=1)  # clean values are never 0
    np.testing.assert_allclose(dropped, p, atol=4 * np.sqrt(0.25 / 3000))
    # Kept values are untouched (no noise configured).
    kept = np.asarray(obs) != 0
    np.testing.assert_array_equal(np.asarray(obs)[kept], np.broadcast_to(np.asarray(clean), obs.shape)[kept])


def test_flicker_probabilities_follow_half_normal():
    s = 0.2
    config = CorruptionConfig(flicker=s)
    keys = jax.random.split(jax.random.key(2), 4000)
    p = jax.vmap(lambda k: corruption_reset(config, k, jnp.ones(OBS_DIM))[0].flicker_p)(keys)
    # E|N(0, s^2)| = s * sqrt(2 / pi)
    np.testing.assert_allclose(np.asarray(p).mean(), s * np.sqrt(2 / np.pi), rtol=0.03)


@pytest.mark.parametrize("delay", [1, 3, 10])
def test_delay_delivers_in_order_with_bounded_age(delay):
    config = CorruptionConfig(delay=delay)
    T = 600
    clean = _clean(T)
    obs, dt, tau, _ = jax.jit(lambda k: _stream(config, clean, k))(jax.random.key(delay))
    obs, dt, tau = np.asarray(obs), np.asarray(dt), np.asarray(tau)
    t = np.arange(T)
    assert np.all(np.diff(tau) >= 0), "observations must arrive in order"
    assert np.all(t - tau >= 0) and np.all(t - tau <= delay)
    assert np.all(dt >= 0)
    np.testing.assert_array_equal(np.cumsum(dt[1:]), tau[1:])  # Δt sums to elapsed capture time
    np.testing.assert_array_equal(obs, np.asarray(clean)[tau])  # delivered = captured at τ_t
    # Lags actually vary over the full range and repeats (Δt = 0) happen.
    assert set(np.unique(t - tau)) == set(range(delay + 1))
    assert (dt == 0).any() and (dt > 1).any()


def test_delay_zero_is_identity():
    clean = _clean(50)
    obs, dt, tau, _ = _stream(CorruptionConfig(), clean, jax.random.key(0))
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(clean))
    np.testing.assert_array_equal(np.asarray(tau), np.arange(50))
    np.testing.assert_array_equal(np.asarray(dt), 1.0)


def test_remove_vel_drops_velocity_key():
    for task, full, without in [("cartpole-swingup", 5, 3), ("acrobot-swingup", 6, 4), ("walker-run", 24, 15)]:
        keys = envs.TASKS[task].obs_keys
        assert sum(size for _, size in keys) == full
        idx = kept_indices(keys, CorruptionConfig(remove_vel=True))
        assert idx.tolist() == list(range(without))  # velocity is the last key in all three domains
        assert kept_indices(keys, CorruptionConfig()).tolist() == list(range(full))


@pytest.fixture(scope="module")
def combined_env():
    env = envs.make("cartpole-swingup", remove_vel=True, obs_noise=0.1, flicker=0.2, delay=3)
    T = 40

    def episode(key):
        k_reset, k_act = jax.random.split(key)
        state = env.reset(k_reset)
        actions = jax.random.uniform(k_act, (T, env.action_size), minval=-1, maxval=1)

        def body(state, action):
            state = env.step(state, action)
            return state, (state.obs, state.dt, state.clean_obs)

        _, out = jax.lax.scan(body, state, actions)
        return out

    # seeds x environments
    return env, jax.jit(jax.vmap(jax.vmap(episode)))


def test_env_corruptions_under_jit_and_vmap(combined_env):
    env, run = combined_env
    assert env.observation_size == 3
    keys = jax.random.split(jax.random.key(0), 6).reshape(2, 3)
    obs, dt, clean = run(keys)
    assert obs.shape == (2, 3, 40, 3) and dt.shape == (2, 3, 40) and clean.shape == (2, 3, 40, 5)
    assert np.all(np.isfinite(np.asarray(obs))) and np.all(np.asarray(dt) >= 0)
    # Reproducible for a fixed key, different across keys.
    obs_again, dt_again, _ = run(keys)
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(obs_again))
    np.testing.assert_array_equal(np.asarray(dt), np.asarray(dt_again))
    flat = np.asarray(obs).reshape(6, -1)
    for i in range(6):
        for j in range(i + 1, 6):
            assert not np.allclose(flat[i], flat[j])
    # The corruption is real: observations differ from the clean kept dimensions.
    assert np.abs(np.asarray(obs) - np.asarray(clean)[..., :3]).mean() > 0.05


def test_same_physics_different_corruption_seeds(combined_env):
    """Two keys that share the physics seed still get independent corruptions (noise drawn per env key)."""
    env, _ = combined_env
    reset_to = jax.jit(env.reset_to)
    state_a = reset_to(jnp.array([0.0, 3.0]), jnp.zeros(2), jax.random.key(1))
    state_b = reset_to(jnp.array([0.0, 3.0]), jnp.zeros(2), jax.random.key(2))
    np.testing.assert_array_equal(np.asarray(state_a.clean_obs), np.asarray(state_b.clean_obs))
    assert not np.allclose(np.asarray(state_a.obs), np.asarray(state_b.obs))
