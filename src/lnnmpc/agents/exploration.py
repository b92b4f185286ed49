"""Colored exploration noise: Gaussian sequences with power spectrum ∝ 1/f^β over a whole episode (JAX, jittable).

TD-MPC2 explores in training by adding the planner's std times white noise to the executed action, drawn anew at
every step. While the value has seen no reward yet MPPI's elites are random, so the executed actions are white
noise, which on cartpole-swingup-sparse reaches the rewarded region in 2% of episodes against 29% for pink noise
(β = 1) drawn over the episode (``experiments/results/random-exploration-sparse-cpu``; Eberhard et al., "Pink
noise is all you need", ICLR 2023). With ``LoopConfig.explore_noise_beta`` the training loop draws one such
sequence per environment at each episode start and hands step t's sample to the planner in place of the white
draw (:func:`lnnmpc.agents.mppi.mppi_plan`'s ``explore_noise``).

:func:`shape_spectrum` is the pure transform (tested against float64 numpy), :func:`colored_noise` draws.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def spectrum_amplitude(steps: int, beta: float) -> jax.Array:
    """(steps // 2 + 1,) amplitudes f^(−β/2) of the real FFT's frequencies f = k / steps, f_0 taken as f_1 (no
    infinite power at zero frequency)."""
    freqs = jnp.fft.rfftfreq(steps)
    freqs = freqs.at[0].set(freqs[1])
    return freqs ** (-beta / 2.0)


def shape_spectrum(real: jax.Array, imag: jax.Array, beta: float, steps: int) -> jax.Array:
    """Colored sequences (steps, ...) from standard normal Fourier coefficients ``real``, ``imag`` (steps // 2 + 1,
    ...): the coefficients scaled by :func:`spectrum_amplitude` (the zero and, for even ``steps``, the Nyquist
    frequency kept real), transformed back, then each sequence standardised to mean 0 and std 1 over its steps."""
    amplitude = spectrum_amplitude(steps, beta).reshape((-1,) + (1,) * (real.ndim - 1))
    imag = imag.at[0].set(0.0)
    if steps % 2 == 0:
        imag = imag.at[-1].set(0.0)
    noise = jnp.fft.irfft(amplitude * (real + 1j * imag), n=steps, axis=0)
    noise = noise - noise.mean(axis=0)
    return noise / jnp.maximum(noise.std(axis=0), 1e-12)


def colored_noise(key: jax.Array, beta: float, steps: int, shape: tuple[int, ...] = ()) -> jax.Array:
    """(steps, *shape) float32 sequences of unit variance with power spectrum ∝ 1/f^β along the first axis,
    independent across ``shape`` (β = 0: white, 1: pink, 2: red). ``steps`` >= 2."""
    if steps < 2:
        raise ValueError(f"colored noise needs steps >= 2, got {steps}")
    k_real, k_imag = jax.random.split(key)
    coefficients = (steps // 2 + 1,) + tuple(shape)
    return shape_spectrum(jax.random.normal(k_real, coefficients), jax.random.normal(k_imag, coefficients),
                          beta, steps).astype(jnp.float32)
