"""TD(λ) targets (agents/returns.py) against a float64 numpy reference, including λ = 0 and λ = 1."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.agents.returns import lambda_returns

H, B = 7, 5


def _np_lambda_returns(rewards, next_values, gamma, lam):
    """Forward definition: R_t = sum over n-step returns weighted (1 - λ) λ^(n-1), the rest on the H - t step one."""
    rewards, next_values = np.asarray(rewards, np.float64), np.asarray(next_values, np.float64)
    horizon = len(rewards)
    out = np.zeros_like(rewards)
    for t in range(horizon):
        remaining = horizon - t

        def n_step(n, t=t):
            discounts = gamma ** np.arange(n)
            return (discounts[:, None] * rewards[t:t + n]).sum(0) + gamma ** n * next_values[t + n - 1]

        total = sum((1 - lam) * lam ** (n - 1) * n_step(n) for n in range(1, remaining))
        out[t] = total + lam ** (remaining - 1) * n_step(remaining)
    return out


@pytest.fixture(scope="module")
def data():
    k1, k2 = jax.random.split(jax.random.key(0))
    return jax.random.normal(k1, (H, B)), 3.0 * jax.random.normal(k2, (H, B))


@pytest.mark.parametrize("lam", [0.0, 0.5, 0.95, 1.0])
def test_lambda_returns_match_numpy_reference(data, lam):
    rewards, values = data
    got = jax.jit(lambda r, v: lambda_returns(r, v, 0.99, lam))(rewards, values)
    np.testing.assert_allclose(np.asarray(got), _np_lambda_returns(rewards, values, 0.99, lam), rtol=1e-5, atol=1e-5)


def test_lambda_edge_cases_are_td0_and_monte_carlo(data):
    rewards, values = (np.asarray(x, np.float64) for x in data)
    gamma = 0.9
    td0 = lambda_returns(jnp.asarray(rewards), jnp.asarray(values), gamma, 0.0)
    np.testing.assert_allclose(np.asarray(td0), rewards + gamma * values, rtol=1e-5, atol=1e-5)
    mc = np.asarray(lambda_returns(jnp.asarray(rewards), jnp.asarray(values), gamma, 1.0))
    for t in range(H):
        expected = sum(gamma ** k * rewards[t + k] for k in range(H - t)) + gamma ** (H - t) * values[-1]
        np.testing.assert_allclose(mc[t], expected, rtol=1e-5, atol=1e-5)


def test_lambda_returns_reject_mismatched_shapes():
    with pytest.raises(ValueError, match=r"rewards \(3, 2\) and next_values \(3, 1\)"):
        lambda_returns(jnp.zeros((3, 2)), jnp.zeros((3, 1)), 0.99, 0.95)


def test_static_lambda_zero_skips_the_scan_and_equals_the_traced_path(data):
    rewards, values = data
    shortcut = jax.jit(lambda r, v: lambda_returns(r, v, 0.99, 0.0))
    traced = jax.jit(lambda r, v, lam: lambda_returns(r, v, 0.99, lam))  # λ traced: the backward scan
    np.testing.assert_allclose(np.asarray(shortcut(rewards, values)),
                               np.asarray(traced(rewards, values, jnp.float32(0.0))), rtol=1e-6, atol=1e-6)
    assert "scan" not in str(jax.make_jaxpr(lambda r, v: lambda_returns(r, v, 0.99, 0))(rewards, values))
    assert "scan" in str(jax.make_jaxpr(lambda r, v: lambda_returns(r, v, 0.99, 0.5))(rewards, values))
