"""TD-MPC2 math pieces against independent float64 numpy references."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.agents import math as M

NB, VMIN, VMAX = 101, -10.0, 10.0


def np_symlog(x):
    return np.sign(x) * np.log(1.0 + np.abs(x))


def np_two_hot(x, nb=NB, vmin=VMIN, vmax=VMAX):
    """Reference: distribute mass on the two neighbouring bins of clip(symlog x), loop per scalar."""
    x = np.asarray(x, np.float64).ravel()
    bins = np.linspace(vmin, vmax, nb)
    out = np.zeros((x.size, nb))
    for i, v in enumerate(np.clip(np_symlog(x), vmin, vmax)):
        j = min(int(np.searchsorted(bins, v, side="right")) - 1, nb - 2)
        w = (v - bins[j]) / (bins[j + 1] - bins[j])
        out[i, j], out[i, j + 1] = 1.0 - w, w
    return out


def np_log_softmax(z):
    z = z - z.max(-1, keepdims=True)
    return z - np.log(np.exp(z).sum(-1, keepdims=True))


def test_symlog_symexp_inverse():
    x = jnp.asarray([-1e4, -3.5, -1e-3, 0.0, 2e-4, 1.0, 7.0, 2e4])
    np.testing.assert_allclose(M.symexp(M.symlog(x)), x, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(M.symlog(x), np_symlog(np.asarray(x, np.float64)), rtol=1e-6, atol=1e-7)
    y = jnp.linspace(-9.0, 9.0, 37)
    np.testing.assert_allclose(M.symlog(M.symexp(y)), y, rtol=1e-5, atol=1e-5)


def test_two_hot_matches_numpy_and_round_trips():
    limit = float(np.expm1(VMAX))  # symexp(vmax) ~ 22025
    x = np.concatenate([np.linspace(-limit, limit, 50), [-3.0, -0.1, 0.0, 0.05, 1.0, 250.0, limit, -limit]])
    enc = M.two_hot(jnp.asarray(x, jnp.float32))
    assert enc.shape == (x.size, NB)
    np.testing.assert_allclose(enc.sum(-1), 1.0, atol=1e-6)
    assert int((enc > 0).sum(-1).max()) <= 2
    np.testing.assert_allclose(enc, np_two_hot(x), atol=2e-5)
    # symexp(softmax(log(two_hot)) . bins) recovers x (exact in symlog space, up to float32)
    dec = M.two_hot_inv(jnp.log(enc))
    np.testing.assert_allclose(np_symlog(np.asarray(dec, np.float64)), np_symlog(x), atol=1e-4)
    np.testing.assert_allclose(dec, x, rtol=1e-3, atol=1e-4)
    # outside the support: clipped to +-symexp(vmax)
    out = M.two_hot_inv(jnp.log(M.two_hot(jnp.asarray([-1e6, 5e4, 1e9]))))
    np.testing.assert_allclose(out, [-limit, limit, limit], rtol=1e-3)
    # batched shapes
    assert M.two_hot(jnp.zeros((3, 4))).shape == (3, 4, NB)
    assert M.two_hot_inv(jnp.zeros((3, 4, NB))).shape == (3, 4)
    np.testing.assert_allclose(M.two_hot_inv(jnp.zeros((2, NB))), 0.0, atol=1e-5)  # uniform -> symmetric mean 0


def test_soft_cross_entropy_matches_numpy():
    rng = np.random.default_rng(0)
    logits = rng.normal(size=(4, 5, NB)) * 3.0
    target = rng.normal(size=(4, 5)) * 30.0
    target[0, 0], target[0, 1] = 1e6, -1e6  # clipped targets
    got = M.soft_cross_entropy(jnp.asarray(logits, jnp.float32), jnp.asarray(target, jnp.float32))
    ref = -(np_two_hot(target).reshape(4, 5, NB) * np_log_softmax(logits)).sum(-1)
    assert got.shape == (4, 5)
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)
    # gradient wrt logits is softmax - two_hot
    g = jax.grad(lambda z: M.soft_cross_entropy(z, jnp.asarray(target[0, 2], jnp.float32)))(
        jnp.asarray(logits[0, 2], jnp.float32)
    )
    ref_g = np.exp(np_log_softmax(logits[0, 2])) - np_two_hot([target[0, 2]])[0]
    np.testing.assert_allclose(g, ref_g, atol=1e-5)


def test_simnorm_groups_sum_to_one_and_match_numpy():
    x = np.random.default_rng(1).normal(size=(3, 7, 64)) * 4.0
    y = np.asarray(M.simnorm(jnp.asarray(x, jnp.float32), 8))
    assert y.shape == x.shape
    np.testing.assert_allclose(y.reshape(3, 7, 8, 8).sum(-1), 1.0, atol=1e-5)
    g = x.reshape(3, 7, 8, 8)
    ref = (np.exp(g - g.max(-1, keepdims=True)) / np.exp(g - g.max(-1, keepdims=True)).sum(-1, keepdims=True))
    np.testing.assert_allclose(y, ref.reshape(x.shape), atol=1e-6)
    # groups are independent: a different group size gives a different result
    assert not np.allclose(np.asarray(M.simnorm(jnp.asarray(x, jnp.float32), 4)), y)


def test_squash_log_prob_matches_change_of_variables():
    rng = np.random.default_rng(2)
    mean = rng.uniform(-1.0, 1.0, size=(16, 6))
    raw = rng.normal(size=(16, 6)) * 0.5
    eps = rng.normal(size=(16, 6)) * 0.6
    log_std = -10.0 + 0.5 * 12.0 * (np.tanh(raw) + 1.0)
    np.testing.assert_allclose(M.log_std_from_raw(jnp.asarray(raw, jnp.float32)), log_std, rtol=1e-5, atol=1e-5)
    u = mean + np.exp(log_std) * eps
    # reference: log N(u; mean, std) - sum log |d tanh / du|, with d tanh/du = 1 / cosh^2(u)
    log_gauss = (-0.5 * ((u - mean) / np.exp(log_std)) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
    ref = log_gauss + 2.0 * np.log(np.cosh(u)).sum(-1)
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    lp = M.gaussian_log_prob(f32(eps), f32(log_std))
    np.testing.assert_allclose(lp, log_gauss, rtol=1e-5, atol=1e-4)
    mu_t, pi_t, log_pi = M.squash(f32(mean), f32(u), lp)
    np.testing.assert_allclose(mu_t, np.tanh(mean), atol=1e-6)
    np.testing.assert_allclose(pi_t, np.tanh(u), atol=1e-6)
    np.testing.assert_allclose(log_pi, ref, rtol=1e-4, atol=2e-3)


def test_sample_tanh_gaussian():
    key = jax.random.PRNGKey(3)
    mean = jnp.asarray(np.random.default_rng(3).normal(size=(5, 4)), jnp.float32)
    raw = jnp.zeros((5, 4))  # log_std = -4
    s = M.sample_tanh_gaussian(key, mean, raw)
    action, log_prob, mean_action = s[:3]
    assert action.shape == (5, 4) and log_prob.shape == (5,) and s.scaled_entropy.shape == (5,)
    assert float(jnp.abs(action).max()) < 1.0
    np.testing.assert_allclose(mean_action, np.tanh(np.asarray(mean)), atol=1e-6)
    eps = np.asarray(jax.random.normal(key, mean.shape), np.float64)
    u = np.asarray(mean, np.float64) + np.exp(-4.0) * eps
    np.testing.assert_allclose(action, np.tanh(u), atol=1e-5)
    log_gauss = (-0.5 * eps**2 + 4.0 - 0.5 * np.log(2 * np.pi)).sum(-1)
    np.testing.assert_allclose(s.scaled_entropy, -4 * log_gauss, rtol=1e-5)
    np.testing.assert_allclose(log_prob, log_gauss + 2.0 * np.log(np.cosh(u)).sum(-1), rtol=1e-4, atol=1e-3)
    # different keys give different samples; jit works
    s2 = jax.jit(M.sample_tanh_gaussian)(jax.random.PRNGKey(4), mean, raw)
    assert not np.allclose(s2.action, action)


def test_running_scale_against_numpy_percentiles():
    rng = np.random.default_rng(4)
    state = M.ScaleState.create()
    assert float(state.value) == 1.0
    x = rng.normal(size=(256, 1)) * 50.0 + 10.0
    rng_ref = np.percentile(x, 95) - np.percentile(x, 5)
    np.testing.assert_allclose(M.batch_percentile_range(jnp.asarray(x, jnp.float32)), rng_ref, rtol=1e-5)
    new = jax.jit(M.update_scale)(state, jnp.asarray(x, jnp.float32))
    np.testing.assert_allclose(new.value, 1.0 + 0.01 * (rng_ref - 1.0), rtol=1e-6)
    # two more updates: value follows the lerp recursion
    ref_v = 1.0 + 0.01 * (rng_ref - 1.0)
    for scale in (3.0, 200.0):
        xb = rng.normal(size=(33,)) * scale
        r = max(np.percentile(xb, 95) - np.percentile(xb, 5), 1.0)
        ref_v = ref_v + 0.5 * (r - ref_v)
        new = M.update_scale(new, jnp.asarray(xb, jnp.float32), tau=0.5)
        np.testing.assert_allclose(new.value, ref_v, rtol=1e-5)
    # a batch with a range below 1 is clamped: value stays at 1
    tight = M.update_scale(M.ScaleState.create(), jnp.linspace(0.0, 0.5, 64), tau=0.3)
    np.testing.assert_allclose(tight.value, 1.0)
    np.testing.assert_allclose(M.apply_scale(new, jnp.asarray([2.0, -4.0])), np.asarray([2.0, -4.0]) / ref_v, rtol=1e-5)


def test_polyak_pytree_and_weights():
    target = {"a": jnp.zeros((2, 3)), "b": [jnp.ones(4), jnp.full((), 2.0)]}
    online = {"a": jnp.ones((2, 3)), "b": [jnp.zeros(4), jnp.full((), 4.0)]}
    out = M.polyak(target, online, 0.25)
    assert jax.tree_util.tree_structure(out) == jax.tree_util.tree_structure(target)
    np.testing.assert_allclose(out["a"], 0.25)
    np.testing.assert_allclose(out["b"][0], 0.75)
    np.testing.assert_allclose(out["b"][1], 2.5)
    np.testing.assert_allclose(M.polyak(target, online, 1.0)["b"][1], 4.0)
    np.testing.assert_allclose(M.discounted_weights(4, 0.5), [1.0, 0.5, 0.25, 0.125])
    np.testing.assert_allclose(M.discounted_weights(3, 1.0), [1.0, 1.0, 1.0])


@pytest.mark.parametrize(
    ("call", "needle"),
    [
        (lambda: M.two_hot(jnp.zeros(3), num_bins=1), "num_bins"),
        (lambda: M.two_hot(jnp.zeros(3), num_bins=0), "got 0"),
        (lambda: M.two_hot(jnp.zeros(3), 11, 5.0, -5.0), "vmin=5.0"),
        (lambda: M.two_hot_inv(jnp.zeros((2, 50))), "50"),
        (lambda: M.soft_cross_entropy(jnp.zeros((2, 7)), jnp.zeros(2)), "7"),
        (lambda: M.simnorm(jnp.zeros((2, 20)), 8), "20"),
        (lambda: M.simnorm(jnp.zeros((2, 20)), 0), "group_size"),
        (lambda: M.log_std_from_raw(jnp.zeros(2), 2.0, -10.0), "min_log_std=2.0"),
        (lambda: M.polyak({}, {}, 1.5), "1.5"),
        (lambda: M.update_scale(M.ScaleState.create(), jnp.zeros(4), tau=-0.1), "-0.1"),
        (lambda: M.discounted_weights(0, 0.5), "horizon"),
    ],
)
def test_value_errors_name_bad_values(call, needle):
    with pytest.raises(ValueError, match=needle.replace(".", r"\.")):
        call()


def test_simnorm_error_names_both_sizes():
    with pytest.raises(ValueError, match=r"20.*8"):
        M.simnorm(jnp.zeros((2, 20)), 8)


def _nll_reference(mean, sigma, target):
    """float64 numpy: per-dimension Gaussian NLL and its derivatives w.r.t. the mean and σ."""
    err = target - mean
    per_dim = 0.5 * (err / sigma) ** 2 + np.log(sigma) + 0.5 * np.log(2 * np.pi)
    return per_dim, -err / sigma ** 2, 1.0 / sigma - err ** 2 / sigma ** 3


@pytest.mark.parametrize("beta", [0.0, 0.5, 1.0])
def test_gaussian_nll_loss_values_and_gradients_match_float64(beta):
    rng = np.random.default_rng(7)
    mean, target = rng.normal(size=(2, 5, 4)), rng.normal(size=(2, 5, 4))
    sigma = rng.uniform(0.05, 2.0, size=(2, 5, 4))
    per_dim, d_mean, d_sigma = _nll_reference(mean, sigma, target)
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    loss, nll, floored = M.gaussian_nll_loss(f32(mean), f32(sigma), f32(target), beta)
    np.testing.assert_allclose(nll, per_dim.mean(-1), rtol=1e-5, atol=1e-5)
    weight = sigma ** (2 * beta)  # held constant in the gradient (stop_gradient)
    np.testing.assert_allclose(loss, (weight * per_dim).mean(-1), rtol=1e-5, atol=1e-5)
    assert not np.asarray(floored).any()
    g_mean, g_sigma = jax.grad(lambda m, s: M.gaussian_nll_loss(m, s, f32(target), beta)[0].sum(),
                               argnums=(0, 1))(f32(mean), f32(sigma))
    np.testing.assert_allclose(g_mean, weight * d_mean / 4, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(g_sigma, weight * d_sigma / 4, rtol=1e-4, atol=1e-4)
    if beta == 1.0:  # β-NLL with β = 1: the mean's gradient is the halved squared error's, σ-free
        np.testing.assert_allclose(g_mean, (mean - target) / 4, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("beta", [0.0, 1.0])
def test_gaussian_nll_free_bits_floor_stops_the_gradient(beta):
    mean = jnp.asarray([[0.0, 0.0], [0.0, 0.0]])
    target = jnp.asarray([[0.01, -0.01], [1.0, -1.0]])  # sample 0 predicted closely, sample 1 badly
    sigma = jnp.full((2, 2), 0.1)
    loss, nll, floored = M.gaussian_nll_loss(mean, sigma, target, beta, free_bits=-1.0)
    per_dim, _, _ = _nll_reference(np.zeros((2, 2)), np.full((2, 2), 0.1), np.asarray(target, np.float64))
    assert per_dim[0].mean() < -1.0 < per_dim[1].mean()
    np.testing.assert_array_equal(floored, [True, False])
    np.testing.assert_allclose(nll, np.maximum(per_dim.mean(-1), -1.0), rtol=1e-5)
    if beta == 0:
        np.testing.assert_allclose(loss, np.maximum(per_dim.mean(-1), -1.0), rtol=1e-5)
    g_mean, g_sigma = jax.grad(lambda m, s: M.gaussian_nll_loss(m, s, target, beta, -1.0)[0].sum(),
                               argnums=(0, 1))(mean, sigma)
    assert np.all(np.asarray(g_mean)[0] == 0) and np.all(np.asarray(g_sigma)[0] == 0)
    assert np.all(np.abs(np.asarray(g_mean)[1]) > 0) and np.all(np.abs(np.asarray(g_sigma)[1]) > 0)
