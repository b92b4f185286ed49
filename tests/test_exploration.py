"""Colored exploration noise: the spectral shaping against a float64 numpy reference, the spectra it draws, and the
training loop's use of it (fresh sequences at episode starts, step t's sample handed to the agent)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.agents.exploration import colored_noise, shape_spectrum
from lnnmpc.train.config import ConfigError, TrainConfig
from lnnmpc.train.loop import ExploringTrainState, TrainState
from lnnmpc.train.setup import build_loop


def numpy_colored(real: np.ndarray, imag: np.ndarray, beta: float, steps: int) -> np.ndarray:
    """float64 reference of shape_spectrum for (steps // 2 + 1, n) coefficients."""
    freqs = np.arange(steps // 2 + 1) / steps
    freqs[0] = freqs[1]
    coefficients = freqs[:, None] ** (-beta / 2) * (real + 1j * imag)
    coefficients[0] = coefficients[0].real
    if steps % 2 == 0:
        coefficients[-1] = coefficients[-1].real
    x = np.fft.irfft(coefficients, n=steps, axis=0)
    x = x - x.mean(axis=0)
    return x / x.std(axis=0)


@pytest.mark.parametrize("steps,beta", [(500, 1.0), (501, 2.0), (64, 0.0)])
def test_shape_spectrum_matches_the_float64_reference(steps, beta):
    rng = np.random.default_rng(steps)
    real, imag = rng.standard_normal((2, steps // 2 + 1, 3))
    ours = shape_spectrum(jnp.asarray(real, jnp.float32), jnp.asarray(imag, jnp.float32), beta, steps)
    np.testing.assert_allclose(ours, numpy_colored(real, imag, beta, steps), atol=2e-5)


def test_colored_noise_has_unit_variance_and_the_asked_spectrum():
    steps, n = 512, 256
    for beta, lag1 in ((0.0, (-0.1, 0.1)), (1.0, (0.5, 0.95)), (2.0, (0.95, 1.0))):
        x = np.asarray(colored_noise(jax.random.key(int(beta)), beta, steps, (n,)), np.float64)
        assert x.shape == (steps, n) and x.dtype == np.float64
        np.testing.assert_allclose(x.mean(axis=0), 0.0, atol=1e-5)
        np.testing.assert_allclose(x.std(axis=0), 1.0, atol=1e-4)
        r = np.mean([np.corrcoef(x[:-1, i], x[1:, i])[0, 1] for i in range(n)])
        assert lag1[0] < r < lag1[1], (beta, r)
        power = (np.abs(np.fft.rfft(x, axis=0)) ** 2).mean(axis=1)[1:]  # mean periodogram, f > 0
        freqs = np.fft.rfftfreq(steps)[1:]
        slope = np.polyfit(np.log(freqs), np.log(power), 1)[0]
        assert abs(slope + beta) < 0.2, (beta, slope)
    with pytest.raises(ValueError, match="steps >= 2"):
        colored_noise(jax.random.key(0), 1.0, 1)


def test_loop_draws_fresh_noise_at_episode_starts_and_hands_the_step_sample_to_the_agent():
    """... and a training chunk makes ``updates_per_step`` updates per agent step of each environment (each update
    counted here in place of learning, so that only acting is compiled)."""
    config = TrainConfig(task="cartpole-swingup", agent="tdmpc2", small=True, envs=2, steps=1000, seed_steps=0,
                         replay_capacity=2100, compile_cache="", explore_noise_beta=1.0, updates_per_step=3)
    loop = build_loop(config)
    assert loop.config.explore_noise_beta == 1.0 and loop.config.updates_per_step == 3
    loop._update = lambda ts, key: (ts.replace(agent=ts.agent.replace(updates=ts.agent.updates + 1)), {})
    ts = jax.jit(loop.init)(jax.random.key(0))
    assert isinstance(ts, ExploringTrainState) and ts.explore_noise.shape == (2, 500, 1)
    ts = ts.replace(env=ts.env.replace(t=jnp.array([0, 7], jnp.int32)))  # env 0 starts an episode, env 1 is at t=7
    new, sample = loop._exploration(ts, ts.env.t == 0, jax.random.key(1))
    old, fresh = np.asarray(ts.explore_noise), np.asarray(new.explore_noise)
    np.testing.assert_array_equal(fresh[1], old[1])  # a running episode keeps its sequence
    assert not np.allclose(fresh[0], old[0])  # a starting one draws a new one
    np.testing.assert_array_equal(np.asarray(sample), np.stack([fresh[0, 0], old[1, 7]]))
    # a training chunk runs with it (the agent's act takes the samples), and a loop without it keeps TrainState
    out, metrics = jax.jit(lambda t: loop.train_chunk(t, 2))(ts)
    assert isinstance(out, ExploringTrainState) and np.isfinite(np.asarray(metrics["reward"])).all()
    assert int(out.agent.updates) - int(ts.agent.updates) == 2 * 2 * 3  # iterations x environments x updates
    plain = build_loop(TrainConfig(task="cartpole-swingup", agent="tdmpc2", small=True, envs=2, steps=1000,
                                   seed_steps=0, replay_capacity=2100, compile_cache=""))
    assert type(jax.eval_shape(plain.init, jax.random.key(0))) is TrainState


def test_colored_seed_phase_acts_with_each_episodes_sequence_clipped():
    """``seed_noise_beta``: the seed phase's actions are the environments' colored sequences at their steps,
    clipped to [-1, 1] (the replay records them), fresh ones at episode starts; without it the seed phase keeps
    its uniform actions and the plain state."""
    config = TrainConfig(task="cartpole-swingup", agent="tdmpc2", small=True, envs=2, steps=1000, seed_steps=0,
                         replay_capacity=2100, compile_cache="", seed_noise_beta=1.0)
    loop = build_loop(config)
    assert loop.config.seed_noise_beta == 1.0 and loop.config.explore_noise_beta is None
    ts = jax.jit(loop.init)(jax.random.key(0))
    assert isinstance(ts, ExploringTrainState)
    ts = ts.replace(env=ts.env.replace(t=jnp.array([3, 7], jnp.int32)))  # two running episodes
    noise = np.asarray(ts.explore_noise)
    out, _ = jax.jit(lambda t: loop.seed_chunk(t, 4))(ts)
    np.testing.assert_array_equal(np.asarray(out.explore_noise), noise)  # no episode started: same sequences
    actions = np.asarray(out.replay.fields["action"])[:4]  # (4 steps, 2 envs, 1)
    expected = np.stack([np.clip(noise[[0, 1], [3 + k, 7 + k]], -1, 1) for k in range(4)])
    np.testing.assert_allclose(actions, expected, rtol=1e-6, atol=1e-6)
    assert np.abs(expected).max() <= 1.0 and np.abs(noise[:, 3:11]).max() > 0.0
    # the training chunk afterwards explores with the agent's own white noise (explore_noise_beta None)
    assert loop._exploration(out, out.env.t == 0, jax.random.key(2))[1] is None
    plain = build_loop(TrainConfig(task="cartpole-swingup", agent="tdmpc2", small=True, envs=2, steps=1000,
                                   seed_steps=0, replay_capacity=2100, compile_cache=""))
    plain_ts, _ = jax.eval_shape(lambda t: plain.seed_chunk(t, 2), jax.eval_shape(plain.init, jax.random.key(0)))
    assert type(plain_ts) is TrainState  # traced only: the state's class is what the check needs


@pytest.mark.parametrize("name", ["explore_noise_beta", "seed_noise_beta"])
@pytest.mark.parametrize("beta", [-0.5, 5.0, True, "pink"])
def test_config_refuses_an_impossible_noise_exponent(name, beta):
    with pytest.raises(ConfigError, match=rf"{name} must be a number in \[0, 4\]"):
        TrainConfig(task="cartpole-swingup", **{name: beta})
