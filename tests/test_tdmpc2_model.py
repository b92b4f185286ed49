"""TD-MPC2 world model: sizes, shapes, initialisation and validation."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.agents.math import simnorm
from lnnmpc.agents.tdmpc2_model import WorldModelConfig, count_parameters, init_world_model, q_logits_of_heads


@pytest.fixture(scope="module")
def small():
    config = WorldModelConfig.from_size(5, 1, 1, enc_dim=32, mlp_dim=32, latent_dim=16, num_q=3)
    model, variables = init_world_model(config, jax.random.key(0))
    return config, model, variables


@pytest.mark.parametrize("size,low,high", [(1, 0.9e6, 1.5e6), (5, 4.0e6, 6.0e6)])
def test_parameter_counts_match_the_size_names(size, low, high):
    config = WorldModelConfig.from_size(24, 6, size)
    variables = jax.eval_shape(lambda k: init_world_model(config, k)[1], jax.random.key(0))
    assert low < count_parameters(variables) < high


def test_shapes_simnorm_and_zero_initialised_heads(small):
    config, model, variables = small
    obs, action = jnp.ones((7, 5)), jnp.ones((7, 1))
    z = model.apply(variables, obs, method="encode")
    assert z.shape == (7, 16)
    np.testing.assert_allclose(np.asarray(z).reshape(7, 2, 8).sum(-1), 1.0, rtol=1e-5)  # SimNorm groups of 8
    z_next = model.apply(variables, z, action, method="next")
    assert z_next.shape == (7, 16) and np.all(np.asarray(z_next) >= 0)
    reward = model.apply(variables, z, action, method="reward")
    q = model.apply(variables, z, action, method="q")
    assert reward.shape == (7, 101) and q.shape == (3, 7, 101)
    assert float(jnp.abs(reward).max()) == 0.0 and float(jnp.abs(q).max()) == 0.0
    mean, raw_log_std = model.apply(variables, z, method="policy")
    assert mean.shape == raw_log_std.shape == (7, 1)


def test_q_heads_are_independent_and_dropout_is_train_only(small):
    config, model, variables = small
    first_kernels = variables["params"]["q_heads"]["Dense_0"]["kernel"]  # (num_q, in, width)
    assert first_kernels.shape[0] == 3
    assert not np.allclose(first_kernels[0], first_kernels[1])
    # Give the output layers weights so Q depends on the hidden layer, then compare train vs eval.
    params = jax.tree_util.tree_map(lambda x: x, variables["params"])
    params["q_heads"]["Dense_2"]["kernel"] = jnp.ones_like(params["q_heads"]["Dense_2"]["kernel"])
    z, a = jnp.ones((4, 16)) / 8, jnp.ones((4, 1))
    evals = [model.apply({"params": params}, z, a, method="q") for _ in range(2)]
    np.testing.assert_array_equal(np.asarray(evals[0]), np.asarray(evals[1]))
    train = model.apply({"params": params}, z, a, False, method="q", rngs={"dropout": jax.random.key(1)})
    assert not np.allclose(np.asarray(train), np.asarray(evals[0]))


def _numpy_head(params: dict, head: int, x: np.ndarray) -> np.ndarray:
    """One Q head in float64 numpy: (Dense -> LayerNorm -> Mish) x 2 -> Dense."""
    p = jax.tree_util.tree_map(lambda a: np.asarray(a[head], np.float64), params)
    for i in range(2):
        x = x @ p[f"Dense_{i}"]["kernel"] + p[f"Dense_{i}"]["bias"]
        x = (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + 1e-5)
        x = x * p[f"LayerNorm_{i}"]["scale"] + p[f"LayerNorm_{i}"]["bias"]
        x = x * np.tanh(np.log1p(np.exp(x)))
    return x @ p["Dense_2"]["kernel"] + p["Dense_2"]["bias"]


def test_each_q_head_matches_its_own_numpy_mlp_on_batched_inputs(small):
    """The ensemble (input broadcast over heads, the head axis in front) computes head i with head i's parameters
    alone, for inputs with several batch axes (as the update's (positions, batch) and a vmap over seeds give)."""
    config, model, variables = small
    rng = np.random.default_rng(0)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(rng.normal(0, 0.3, a.shape), a.dtype), variables["params"])
    z, a = rng.normal(size=(2, 5, 16)).astype(np.float32), rng.normal(size=(2, 5, 1)).astype(np.float32)
    q = np.asarray(model.apply({"params": params}, z, a, method="q"))
    assert q.shape == (config.num_q, 2, 5, 101)
    x = np.concatenate([z, a], axis=-1).astype(np.float64)
    for head in range(config.num_q):
        np.testing.assert_allclose(q[head], _numpy_head(params["q_heads"], head, x), rtol=2e-4, atol=2e-4)
    seeds = jax.vmap(lambda zz, aa: model.apply({"params": params}, zz, aa, method="q"))(z, a)  # batch over axis 0
    np.testing.assert_allclose(np.asarray(seeds).transpose(1, 0, 2, 3), q, rtol=1e-5, atol=1e-5)


def test_chosen_heads_alone_match_their_numpy_mlps_and_the_full_ensemble(small):
    """q_logits_of_heads computes only the chosen heads (any order, under jit), each with its own parameters; with a
    dropout key each chosen head draws its own mask, and dropout stays off without one."""
    config, model, variables = small
    rng = np.random.default_rng(1)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(rng.normal(0, 0.3, a.shape), a.dtype), variables["params"])
    z, a = rng.normal(size=(4, 16)).astype(np.float32), rng.normal(size=(4, 1)).astype(np.float32)
    full = np.asarray(model.apply({"params": params}, z, a, method="q"))
    x = np.concatenate([z, a], axis=-1).astype(np.float64)
    chosen = jax.jit(lambda h: q_logits_of_heads(config, params["q_heads"], h, z, a))
    for heads in ([2, 0], [1, 2], [0], [2, 0, 1]):  # the last: every head (the ensemble as it is, reordered)
        q = np.asarray(chosen(jnp.array(heads)))
        assert q.shape == (len(heads), 4, 101)
        np.testing.assert_allclose(q, full[heads], rtol=1e-5, atol=1e-5)
        for i, head in enumerate(heads):
            np.testing.assert_allclose(q[i], _numpy_head(params["q_heads"], head, x), rtol=2e-4, atol=2e-4)
    # the same head twice with dropout (at 0.5, so that a mask surely drops something): two different masks, so
    # two outputs, neither equal to the eval output
    dropping = dataclasses.replace(config, q_dropout=0.5)
    twice = np.asarray(q_logits_of_heads(dropping, params["q_heads"], jnp.array([1, 1]), z, a,
                                         dropout_key=jax.random.key(3)))
    assert not np.allclose(twice[0], twice[1]) and not np.allclose(twice[0], full[1])
    # every head with dropout (the liquid agents' 2 of 2): one key's masks, put in the order asked for
    key = jax.random.key(4)
    in_order = np.asarray(q_logits_of_heads(dropping, params["q_heads"], jnp.array([0, 1, 2]), z, a, dropout_key=key))
    reordered = np.asarray(q_logits_of_heads(dropping, params["q_heads"], jnp.array([1, 2, 0]), z, a,
                                             dropout_key=key))
    np.testing.assert_array_equal(reordered, in_order[[1, 2, 0]])
    assert not np.allclose(in_order, full)


def test_simnorm_matches_numpy():
    x = np.random.default_rng(0).normal(size=(3, 16))
    groups = x.reshape(3, 2, 8)
    expected = (np.exp(groups) / np.exp(groups).sum(-1, keepdims=True)).reshape(3, 16)
    np.testing.assert_allclose(np.asarray(simnorm(jnp.asarray(x), 8)), expected, rtol=1e-5)


def test_config_validation():
    with pytest.raises(ValueError, match="unknown model_size 3; known: 1, 5"):
        WorldModelConfig.from_size(5, 1, 3)
    with pytest.raises(ValueError, match="latent_dim 20 must be divisible by simnorm_dim 8"):
        WorldModelConfig(obs_dim=5, action_dim=1, latent_dim=20)
    with pytest.raises(ValueError, match="num_q must be an integer >= 2"):
        WorldModelConfig(obs_dim=5, action_dim=1, num_q=1)
    with pytest.raises(ValueError, match="obs_dim must be an integer >= 1, got 0"):
        WorldModelConfig(obs_dim=0, action_dim=1)


@pytest.mark.parametrize("layer_norm", [True, False])
def test_simnorm_outputs_follow_a_layer_norm_and_kernels_are_normal_002(layer_norm):
    """TD-MPC2's encoder and dynamics end Dense -> LayerNorm -> SimNorm: the latent is then unchanged when the
    last Dense's output is scaled (it is not without the LayerNorm, the layout of older runs). Kernels are
    N(0, 0.02²) as torch's trunc_normal_(std=0.02) (cut at ±2 absolute) draws them, not cut at ±2σ."""
    config = WorldModelConfig.from_size(5, 1, 1, enc_dim=64, mlp_dim=64, latent_dim=16, num_q=2,
                                        simnorm_layer_norm=layer_norm)
    model, variables = init_world_model(config, jax.random.key(3))
    obs, action = jax.random.normal(jax.random.key(4), (7, 5)), jnp.ones((7, 1))
    params = jax.tree_util.tree_map(lambda x: x, variables["params"])
    for part in ("encoder", "dynamics"):
        params[part]["Dense_1" if part == "encoder" else "Dense_2"] = jax.tree_util.tree_map(
            lambda x: 10.0 * x, params[part]["Dense_1" if part == "encoder" else "Dense_2"])
    z, z_scaled = (model.apply({"params": p}, obs, method="encode") for p in (variables["params"], params))
    nxt, nxt_scaled = (model.apply({"params": p}, z, action, method="next") for p in (variables["params"], params))
    same = np.allclose(np.asarray(z), np.asarray(z_scaled), atol=1e-2) and np.allclose(
        np.asarray(nxt), np.asarray(nxt_scaled), atol=1e-2)
    assert same == layer_norm  # with it: equal up to the LayerNorm's epsilon (~3e-4); without: ~0.4 apart
    kernel = np.asarray(variables["params"]["dynamics"]["Dense_1"]["kernel"])  # 64 x 64 draws
    assert abs(kernel.std() - 0.02) < 0.002 and np.abs(kernel).max() > 2.2 * 0.02


def test_an_mlp_reading_a_tuple_is_the_mlp_of_its_concatenation():
    """The first layer reads (z, a) without concatenating them: the same parameter names, shapes and initial
    values as the MLP of concatenate([z, a]) under the same key, and the same outputs (float32 rounding apart),
    with a dropout layer and SimNorm output as well."""
    from lnnmpc.agents.tdmpc2_model import MLP

    mlp = MLP((24, 24), 16, simnorm_dim=8, dropout=0.1, output_layer_norm=True)
    rng = np.random.default_rng(2)
    z, a = rng.normal(size=(3, 5, 12)).astype(np.float32), rng.normal(size=(3, 5, 2)).astype(np.float32)
    joined = np.concatenate([z, a], axis=-1)
    split_params = mlp.init(jax.random.key(5), (z, a))
    joined_params = mlp.init(jax.random.key(5), joined)
    assert jax.tree_util.tree_structure(split_params) == jax.tree_util.tree_structure(joined_params)
    for x, y in zip(jax.tree_util.tree_leaves(split_params), jax.tree_util.tree_leaves(joined_params), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # random parameters (the zero biases would hide a wrong bias path)
    params = jax.tree_util.tree_map(lambda p: jnp.asarray(rng.normal(0, 0.3, p.shape), p.dtype), joined_params)
    np.testing.assert_allclose(np.asarray(mlp.apply(params, (z, a))), np.asarray(mlp.apply(params, joined)),
                               rtol=1e-5, atol=1e-6)
    rngs = {"dropout": jax.random.key(6)}
    np.testing.assert_allclose(np.asarray(mlp.apply(params, (z, a), False, rngs=rngs)),
                               np.asarray(mlp.apply(params, joined, False, rngs=rngs)), rtol=1e-5, atol=1e-6)
    grads = [jax.grad(lambda p, x: mlp.apply(p, x).sum())(params, x) for x in ((z, a), joined)]
    for x, y in zip(*map(jax.tree_util.tree_leaves, grads), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=1e-5)


def test_the_world_model_keeps_its_parameter_names():
    """Checkpoints and policy files of earlier runs load: every component's layers keep nn.Dense's names."""
    config = WorldModelConfig.from_size(5, 1, 1, enc_dim=32, mlp_dim=32, latent_dim=16, num_q=2)
    params = init_world_model(config, jax.random.key(0))[1]["params"]
    normed = ["LayerNorm_2"] if config.simnorm_layer_norm else []  # the SimNorm outputs' LayerNorm
    expected = {"encoder": ["Dense_0", "Dense_1", "LayerNorm_0"] + (["LayerNorm_1"] if normed else []),
                "dynamics": ["Dense_0", "Dense_1", "Dense_2", "LayerNorm_0", "LayerNorm_1", *normed]}
    expected |= {head: ["Dense_0", "Dense_1", "Dense_2", "LayerNorm_0", "LayerNorm_1"]
                 for head in ("reward_head", "policy_head", "q_heads")}
    assert {part: sorted(layers) for part, layers in params.items()} == expected
    assert params["dynamics"]["Dense_0"]["kernel"].shape == (16 + 1, 32)
    assert params["q_heads"]["Dense_0"]["kernel"].shape == (2, 16 + 1, 32)
