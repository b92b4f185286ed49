"""Liquid cells and unroll: shapes, Δt handling, resets, gradients, vmap, remat, configs."""

from __future__ import annotations

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.nets import CfCCell, LTCCell, clip_ltc_parameters, unroll

BATCH, INPUTS, HIDDEN = 3, 4, 6
CELLS = {
    "cfc_default": CfCCell(HIDDEN, backbone_units=10),
    "cfc_no_gate": CfCCell(
        HIDDEN, mode="no_gate", backbone_units=10, backbone_layers=2, backbone_activation="gelu"
    ),
    "cfc_pure": CfCCell(HIDDEN, mode="pure", backbone_units=10),
    "ltc": LTCCell(HIDDEN),
    "ltc_explicit_3_outputs": LTCCell(HIDDEN, output_size=3, implicit_param_constraints=False),
}


def init_cell(cell, seed: int = 0):
    key = jax.random.PRNGKey(seed)
    return cell.init(key, jnp.zeros((BATCH, HIDDEN)), jnp.zeros((BATCH, INPUTS)), jnp.ones((BATCH, 1)))


def random_sequence(length: int, seed: int = 1, max_dt: float = 5.0):
    """(inputs (T, B, I), dts (T, B) in [0, max_dt] with exact zeros, initial state (B, H))."""
    k_x, k_dt, k_zero, k_h = jax.random.split(jax.random.PRNGKey(seed), 4)
    inputs = jax.random.normal(k_x, (length, BATCH, INPUTS))
    dts = jax.random.uniform(k_dt, (length, BATCH), maxval=max_dt)
    dts = jnp.where(jax.random.uniform(k_zero, (length, BATCH)) < 0.2, 0.0, dts).at[0].set(0.0)
    return inputs, dts, 0.5 * jax.random.normal(k_h, (BATCH, HIDDEN))


@functools.cache
def jitted_unroll(cell, remat: bool = False):
    def run(variables, h0, xs, dts, resets):
        return unroll(cell, variables, h0, xs, dts, resets, remat=remat)

    return jax.jit(run)


@functools.cache
def jitted_loss_grad(cell, remat: bool = False):
    def loss(variables, h0, xs, dts):
        result = unroll(cell, variables, h0, xs, dts, remat=remat)
        return jnp.mean(result.states**2) + jnp.mean(result.outputs)

    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3)))


@pytest.mark.parametrize("name", CELLS)
def test_unroll_shapes_and_dtypes(name):
    cell = CELLS[name]
    variables = init_cell(cell)
    inputs, dts, h0 = random_sequence(7)
    result = jitted_unroll(cell)(variables, h0, inputs, dts, None)
    out_size = cell.readout_size
    assert result.states.shape == (7, BATCH, HIDDEN) and result.outputs.shape == (7, BATCH, out_size)
    assert result.states.dtype == result.outputs.dtype == jnp.float32
    assert cell.initial_state(BATCH).shape == (BATCH, cell.state_size) and cell.state_size == HIDDEN
    assert out_size == (3 if name == "ltc_explicit_3_outputs" else HIDDEN)
    new_state, output = cell.apply(variables, h0, inputs[0], dts[0])
    np.testing.assert_allclose(new_state, result.states[0], atol=1e-6, rtol=0)  # eager vs jit: rounding only
    np.testing.assert_allclose(output, result.outputs[0], atol=1e-6, rtol=0)
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(variables))


@pytest.mark.parametrize("name", CELLS)
def test_gradients_finite_over_64_steps_with_dt_up_to_5(name):
    cell = CELLS[name]
    variables = init_cell(cell)
    inputs, dts, h0 = random_sequence(64)
    assert float(dts.max()) > 4.0 and bool(jnp.any(dts == 0))
    loss, grads = jitted_loss_grad(cell)(variables, h0, inputs, dts)
    assert np.isfinite(float(loss))
    leaves = jax.tree.leaves(grads)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
    assert any(float(jnp.max(jnp.abs(g))) > 0 for g in jax.tree.leaves(grads[0]))


@pytest.mark.parametrize("name", ["cfc_default", "ltc"])
def test_reset_inside_sequence_equals_restart(name):
    cell = CELLS[name]
    variables = init_cell(cell)
    inputs, dts, h0 = random_sequence(12)
    resets = jnp.zeros((12, BATCH), bool).at[5, 0].set(True).at[5, 2].set(True).at[9, 2].set(True)
    run = jitted_unroll(cell)
    joined = run(variables, h0, inputs, dts, resets)
    first = run(variables, h0, inputs[:5], dts[:5], None)
    second = run(variables, cell.initial_state(BATCH), inputs[5:9], dts[5:9], None)
    third = run(variables, cell.initial_state(BATCH), inputs[9:], dts[9:], None)
    whole = run(variables, h0, inputs, dts, None)
    np.testing.assert_allclose(joined.states[:5], first.states, atol=1e-6, rtol=0)
    np.testing.assert_allclose(joined.states[5:9, 0], second.states[:, 0], atol=1e-6, rtol=0)
    np.testing.assert_allclose(joined.states[5:9, 2], second.states[:, 2], atol=1e-6, rtol=0)
    np.testing.assert_allclose(joined.states[9:, 2], third.states[:, 2], atol=1e-6, rtol=0)
    np.testing.assert_allclose(joined.states[:, 1], whole.states[:, 1], atol=1e-6, rtol=0)  # no reset
    assert float(jnp.max(jnp.abs(joined.states[5:, 0] - whole.states[5:, 0]))) > 1e-3


def test_reset_uses_given_reset_state_and_applies_at_step_zero():
    cell = CELLS["cfc_default"]
    variables = init_cell(cell)
    inputs, dts, h0 = random_sequence(4)
    learned_h0 = jnp.linspace(-1, 1, HIDDEN)
    resets = jnp.zeros((4, BATCH), bool).at[0].set(True)
    joined = unroll(cell, variables, h0, inputs, dts, resets, reset_state=learned_h0)
    fresh = unroll(cell, variables, jnp.broadcast_to(learned_h0, (BATCH, HIDDEN)), inputs, dts)
    np.testing.assert_allclose(joined.states, fresh.states, atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", ["ltc", "ltc_explicit_3_outputs"])
def test_ltc_keeps_state_exactly_when_no_time_elapses(name):
    cell = CELLS[name]
    variables = init_cell(cell)
    inputs, _, h0 = random_sequence(5)
    dts = jnp.zeros((5, BATCH)).at[2, 1].set(0.7)
    result = jitted_unroll(cell)(variables, h0, inputs, dts, None)
    np.testing.assert_array_equal(result.states[:2], jnp.broadcast_to(h0, (2, BATCH, HIDDEN)))
    np.testing.assert_array_equal(result.states[:, 0], jnp.broadcast_to(h0[0], (5, HIDDEN)))
    assert float(jnp.max(jnp.abs(result.states[2, 1] - h0[1]))) > 1e-4
    _, grads = jitted_loss_grad(cell)(variables, h0, inputs, dts)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree.leaves(grads))


def test_ltc_zero_dt_with_zero_capacitance_is_not_nan():
    cell = CELLS["ltc_explicit_3_outputs"]
    variables = init_cell(cell)
    variables = {"params": {**variables["params"], "cm": jnp.zeros(HIDDEN)}}
    _, _, h0 = random_sequence(1)
    new_state, _ = cell.apply(variables, h0, jnp.ones((BATCH, INPUTS)), 0.0)
    np.testing.assert_array_equal(new_state, h0)


def test_cfc_zero_dt_is_finite_and_uses_time_b_only():
    cell = CELLS["cfc_default"]
    variables = init_cell(cell)
    _, _, h0 = random_sequence(1)
    x = jnp.ones((BATCH, INPUTS))
    at_zero, _ = cell.apply(variables, h0, x, 0.0)
    params = dict(variables["params"])
    params["time_a"] = jax.tree.map(lambda p: 10.0 + p, params["time_a"])  # time_a must not matter at Δt=0
    np.testing.assert_array_equal(cell.apply({"params": params}, h0, x, 0.0)[0], at_zero)
    assert bool(jnp.all(jnp.isfinite(at_zero)))


@pytest.mark.parametrize("name", ["cfc_pure", "ltc"])
def test_time_delta_shapes_are_equivalent(name):
    cell = CELLS[name]
    variables = init_cell(cell)
    _, _, h0 = random_sequence(1)
    x = jnp.ones((BATCH, INPUTS))
    column = cell.apply(variables, h0, x, jnp.full((BATCH, 1), 0.5))[0]
    np.testing.assert_array_equal(cell.apply(variables, h0, x, jnp.full((BATCH,), 0.5))[0], column)
    np.testing.assert_array_equal(cell.apply(variables, h0, x, 0.5)[0], column)
    per_sample = jnp.array([0.0, 1.0, 4.0])
    rows = cell.apply(variables, h0, x, per_sample)[0]
    for i, dt in enumerate(per_sample):
        np.testing.assert_allclose(rows[i], cell.apply(variables, h0, x, dt)[0][i], atol=1e-7, rtol=0)
    with pytest.raises(ValueError, match=r"\(2,\)"):
        cell.apply(variables, h0, x, jnp.ones(2))


def test_unroll_time_delta_forms_are_equivalent():
    cell = CELLS["cfc_default"]
    variables = init_cell(cell)
    inputs, _, h0 = random_sequence(4)
    per_step = jnp.array([0.0, 0.5, 1.0, 3.0])
    reference = unroll(cell, variables, h0, inputs, jnp.broadcast_to(per_step[:, None, None], (4, BATCH, 1)))
    for dts in (per_step, jnp.broadcast_to(per_step[:, None], (4, BATCH))):
        np.testing.assert_array_equal(unroll(cell, variables, h0, inputs, dts).states, reference.states)
    np.testing.assert_array_equal(unroll(cell, variables, h0, inputs).states,
                                  unroll(cell, variables, h0, inputs, 1.0).states)
    unrolled_loop = unroll(cell, variables, h0, inputs, per_step, scan_unroll=3).states
    np.testing.assert_allclose(unrolled_loop, reference.states, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="time deltas"):
        unroll(cell, variables, h0, inputs, jnp.ones((5, BATCH)))
    with pytest.raises(ValueError, match="resets"):
        unroll(cell, variables, h0, inputs, 1.0, jnp.zeros((4, BATCH + 1), bool))


@pytest.mark.parametrize("name", ["cfc_default", "ltc"])
def test_vmap_over_seeds_matches_per_seed_loop(name):
    cell = CELLS[name]
    seeds = 3
    keys = jax.random.split(jax.random.PRNGKey(7), seeds)
    stacked = jax.vmap(lambda key: init_cell_with_key(cell, key))(keys)
    inputs, dts, h0 = random_sequence(6)
    per_seed_inputs = inputs + jnp.arange(seeds, dtype=jnp.float32)[:, None, None, None]

    def run(variables, xs):
        return unroll(cell, variables, h0, xs, dts).states

    vmapped = jax.jit(jax.vmap(run))(stacked, per_seed_inputs)
    first_leaf = jax.tree.leaves(stacked["params"])[0]
    assert not np.allclose(first_leaf[0], first_leaf[1])  # independent parameters per seed
    for seed in range(seeds):
        variables = jax.tree.map(lambda leaf, s=seed: leaf[s], stacked)
        np.testing.assert_allclose(vmapped[seed], run(variables, per_seed_inputs[seed]), atol=1e-6, rtol=0)
    assert float(jnp.max(jnp.abs(vmapped[0] - vmapped[1]))) > 1e-4


def init_cell_with_key(cell, key):
    return cell.init(key, jnp.zeros((BATCH, HIDDEN)), jnp.zeros((BATCH, INPUTS)), jnp.ones((BATCH, 1)))


@pytest.mark.parametrize("name", ["cfc_default", "ltc"])
def test_remat_gives_same_values_and_gradients(name):
    cell = CELLS[name]
    variables = init_cell(cell)
    inputs, dts, h0 = random_sequence(10)
    plain_loss, plain_grads = jitted_loss_grad(cell, False)(variables, h0, inputs, dts)
    remat_loss, remat_grads = jitted_loss_grad(cell, True)(variables, h0, inputs, dts)
    np.testing.assert_allclose(remat_loss, plain_loss, rtol=1e-6)
    for remat, plain in zip(jax.tree.leaves(remat_grads), jax.tree.leaves(plain_grads), strict=True):
        np.testing.assert_allclose(remat, plain, atol=1e-6, rtol=1e-5)


def test_ltc_stored_synapses_give_same_values_and_gradients():
    recomputing, storing = CELLS["ltc"], LTCCell(HIDDEN, recompute_synapses=False)
    variables = init_cell(recomputing)
    inputs, dts, h0 = random_sequence(10)
    loss, grads = jitted_loss_grad(recomputing)(variables, h0, inputs, dts)
    stored_loss, stored_grads = jitted_loss_grad(storing)(variables, h0, inputs, dts)
    np.testing.assert_allclose(stored_loss, loss, rtol=1e-6)
    for stored, recomputed in zip(jax.tree.leaves(stored_grads), jax.tree.leaves(grads), strict=True):
        np.testing.assert_allclose(stored, recomputed, atol=1e-6, rtol=1e-5)


def test_backbone_dropout_is_active_only_after_layer_two_and_with_an_rng():
    inputs, dts, h0 = random_sequence(5)
    key = jax.random.PRNGKey(3)
    two_layers = CfCCell(HIDDEN, backbone_units=10, backbone_layers=2, backbone_dropout=0.5)
    variables = init_cell(two_layers)
    deterministic = unroll(two_layers, variables, h0, inputs, dts).states
    dropped = unroll(two_layers, variables, h0, inputs, dts, dropout_rng=key).states
    assert float(jnp.max(jnp.abs(dropped - deterministic))) > 1e-3
    one_layer = CfCCell(HIDDEN, backbone_units=10, backbone_layers=1, backbone_dropout=0.5)
    variables = init_cell(one_layer)
    np.testing.assert_array_equal(unroll(one_layer, variables, h0, inputs, dts, dropout_rng=key).states,
                                  unroll(one_layer, variables, h0, inputs, dts, fused=False).states)


def test_cfc_initialisation_follows_torch_ranges():
    cell = CfCCell(HIDDEN, mode="pure", backbone_units=50)
    params = init_cell(cell)["params"]
    fan_in = INPUTS + HIDDEN
    backbone = params["backbone_0"]
    assert float(jnp.max(jnp.abs(backbone["bias"]))) <= 1 / np.sqrt(fan_in)
    assert float(jnp.max(jnp.abs(backbone["bias"]))) > 0.5 / np.sqrt(fan_in)
    assert float(jnp.max(jnp.abs(backbone["kernel"]))) <= np.sqrt(6 / (fan_in + 50))
    assert float(jnp.max(jnp.abs(params["ff1"]["bias"]))) <= 1 / np.sqrt(50)
    assert params["w_tau"].shape == params["A"].shape == (1, HIDDEN)
    assert float(jnp.max(jnp.abs(params["A"]))) <= np.sqrt(6 / (1 + HIDDEN))
    assert float(jnp.std(params["A"])) > 0.1  # xavier, not ncps's pre-init ones


def test_ltc_initialisation_follows_ncps_ranges():
    params = init_cell(LTCCell(HIDDEN))["params"]
    ranges = {"gleak": (0.001, 1.0), "vleak": (-0.2, 0.2), "cm": (0.4, 0.6), "w": (0.001, 1.0),
              "sigma": (3.0, 8.0), "mu": (0.3, 0.8), "sensory_sigma": (3.0, 8.0)}
    for name, (low, high) in ranges.items():
        assert low <= float(params[name].min()) and float(params[name].max()) <= high, name
    assert set(np.unique(params["erev"])) <= {-1.0, 1.0}
    np.testing.assert_array_equal(params["input_w"], 1.0)
    np.testing.assert_array_equal(params["output_b"], 0.0)


def test_clip_ltc_parameters_clips_only_constrained_ones():
    variables = init_cell(LTCCell(HIDDEN, implicit_param_constraints=False))
    negative = {"params": jax.tree.map(lambda p: -p, variables["params"])}
    clipped = clip_ltc_parameters(negative)["params"]
    for name in ("w", "sensory_w", "cm", "gleak"):
        np.testing.assert_array_equal(clipped[name], 0.0)
    np.testing.assert_array_equal(clipped["sigma"], negative["params"]["sigma"])


@pytest.mark.parametrize(
    ("factory", "bad_value", "allowed"),
    [
        (lambda: CfCCell(8, mode="liquid"), "'liquid'", "pure"),
        (lambda: CfCCell(8, backbone_activation="elu"), "'elu'", "lecun_tanh"),
        (lambda: CfCCell(0), "hidden_size=0", ">= 1"),
        (lambda: CfCCell(8, backbone_units=0), "backbone_units=0", ">= 1"),
        (lambda: CfCCell(8, backbone_layers=-1), "backbone_layers=-1", ">= 0"),
        (lambda: CfCCell(8, backbone_dropout=-0.1), "-0.1", r"\[0, 1\)"),
        (lambda: CfCCell(8, backbone_dropout=1.0), "1.0", r"\[0, 1\)"),
        (lambda: CfCCell(8.0), "hidden_size=8.0", "integer"),
        (lambda: LTCCell(0), "hidden_size=0", ">= 1"),
        (lambda: LTCCell(8, ode_unfolds=0), "ode_unfolds=0", ">= 1"),
        (lambda: LTCCell(8, epsilon=-1e-8), "-1e-08", ">= 0"),
        (lambda: LTCCell(8, output_size=9), "output_size=9", "hidden_size=8"),
        (lambda: LTCCell(8, input_mapping="sigmoid"), "'sigmoid'", "affine"),
        (lambda: LTCCell(8, output_mapping=None), "None", "linear"),
        (lambda: LTCCell(8, implicit_param_constraints="yes"), "'yes'", "True"),
        (lambda: LTCCell(8, manual_backward="no"), "manual_backward='no'", "True"),
    ],
)
def test_bad_configs_raise_value_error_naming_the_value(factory, bad_value, allowed):
    with pytest.raises(ValueError, match=bad_value) as error:
        factory()
    assert re.search(allowed, str(error.value))


FUSED_CASES = {
    **CELLS,
    "cfc_pure_no_backbone": CfCCell(HIDDEN, mode="pure", backbone_layers=0),
    "cfc_default_3_layers_silu": CfCCell(HIDDEN, backbone_units=7, backbone_layers=3, backbone_activation="silu"),
}


@pytest.mark.parametrize("name", FUSED_CASES)
def test_fused_unroll_matches_step_by_step_values_and_gradients(name):
    cell = FUSED_CASES[name]
    variables = init_cell(cell)
    inputs, dts, h0 = random_sequence(12)
    resets = jax.random.bernoulli(jax.random.PRNGKey(5), 0.2, (12, BATCH)).at[0, 0].set(True)
    reset_state = 0.3 * jnp.ones((BATCH, HIDDEN))

    def loss(fused, variables, h0, xs, dts, reset_state):
        result = unroll(cell, variables, h0, xs, dts, resets, reset_state=reset_state, fused=fused)
        return jnp.mean(result.states**2) + jnp.mean(result.outputs * jnp.arange(result.outputs.shape[-1]))

    arguments = (variables, h0, inputs, dts, reset_state)
    grad = jax.value_and_grad(loss, argnums=(1, 2, 3, 4, 5))
    fused_loss, fused_grads = jax.jit(functools.partial(grad, True))(*arguments)
    step_loss, step_grads = jax.jit(functools.partial(grad, False))(*arguments)
    np.testing.assert_allclose(fused_loss, step_loss, rtol=1e-6)
    for fused, step in zip(jax.tree.leaves(fused_grads), jax.tree.leaves(step_grads), strict=True):
        np.testing.assert_allclose(fused, step, atol=1e-6, rtol=1e-5)
    np.testing.assert_allclose(unroll(cell, variables, h0, inputs, dts, resets, fused=True).states,
                               unroll(cell, variables, h0, inputs, dts, resets, fused=False).states, atol=1e-6)


def perturbed_ltc_variables(cell, seed: int):
    """Initial LTC variables plus noise on every parameter (so no symmetry hides a wrong gradient)."""
    variables = init_cell(cell, seed)
    leaves, tree = jax.tree.flatten(variables)
    keys = jax.random.split(jax.random.PRNGKey(100 + seed), len(leaves))
    noisy = [leaf + 0.3 * jax.random.normal(key, leaf.shape) for leaf, key in zip(leaves, keys, strict=True)]
    return jax.tree.unflatten(tree, noisy)


def manual_and_autodiff_cells(**config):
    return LTCCell(HIDDEN, manual_backward=True, **config), LTCCell(HIDDEN, manual_backward=False, **config)


def assert_trees_close(actual, expected, rtol=1e-5):
    for got, want in zip(jax.tree.leaves(actual), jax.tree.leaves(expected), strict=True):
        scale = float(jnp.max(jnp.abs(want))) + 1e-12
        np.testing.assert_allclose(got, want, atol=rtol * scale, rtol=rtol)


@pytest.mark.parametrize("constraints", [True, False])
def test_ltc_manual_backward_matches_autodiff_through_unroll_with_resets(constraints):
    manual, autodiff = manual_and_autodiff_cells(implicit_param_constraints=constraints, output_size=4)
    variables = perturbed_ltc_variables(autodiff, seed=3)
    inputs, dts, h0 = random_sequence(12, seed=4)
    resets = jax.random.bernoulli(jax.random.PRNGKey(6), 0.2, (12, BATCH)).at[0, 1].set(True)
    reset_state = 0.2 * jnp.ones((BATCH, HIDDEN))

    def loss(cell, fused, variables, h0, xs, dts, reset_state):
        result = unroll(cell, variables, h0, xs, dts, resets, reset_state=reset_state, fused=fused)
        return jnp.mean(jnp.sin(3 * result.states)) + jnp.mean(result.outputs * jnp.arange(4))

    arguments = (variables, h0, inputs, dts, reset_state)
    for fused in (True, False):
        grad = jax.jit(jax.value_and_grad(functools.partial(loss, manual, fused), argnums=(0, 1, 2, 3, 4)))
        want = jax.jit(jax.value_and_grad(functools.partial(loss, autodiff, fused), argnums=(0, 1, 2, 3, 4)))
        (value, grads), (want_value, want_grads) = grad(*arguments), want(*arguments)
        assert float(value) == float(want_value)  # identical forward operations
        assert_trees_close(grads, want_grads)
    np.testing.assert_array_equal(unroll(manual, variables, h0, inputs, dts, resets).states,
                                  unroll(autodiff, variables, h0, inputs, dts, resets).states)


def test_ltc_manual_backward_at_zero_dt_and_zero_capacitance():
    manual, autodiff = manual_and_autodiff_cells(implicit_param_constraints=False)
    variables = perturbed_ltc_variables(autodiff, seed=5)
    variables["params"]["cm"] = variables["params"]["cm"].at[:2].set(0.0)
    inputs, _, h0 = random_sequence(3, seed=2)
    dt = jnp.array([0.0, 0.7, 0.0])

    def loss(cell, variables, h0, x, dt):
        new_state, output = cell.apply(variables, h0, x, dt)
        return jnp.sum(new_state**3) + jnp.sum(output)

    grad = jax.grad(functools.partial(loss, manual), argnums=(0, 1, 2, 3))(variables, h0, inputs[0], dt)
    want = jax.grad(functools.partial(loss, autodiff), argnums=(0, 1, 2, 3))(variables, h0, inputs[0], dt)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(grad))
    assert_trees_close(grad, want)


def test_ltc_manual_backward_matches_autodiff_under_vmap_over_seeds_and_remat():
    manual, autodiff = manual_and_autodiff_cells()
    stacked = jax.tree.map(lambda *leaves: jnp.stack(leaves), *[perturbed_ltc_variables(autodiff, s) for s in range(3)])
    inputs, dts, h0 = random_sequence(8, seed=9)

    def loss(cell, remat, variables):
        return jnp.mean(unroll(cell, variables, h0, inputs, dts, remat=remat).states ** 2)

    want = jax.jit(jax.vmap(jax.value_and_grad(functools.partial(loss, autodiff, False))))(stacked)
    for remat in (False, True):
        got = jax.jit(jax.vmap(jax.value_and_grad(functools.partial(loss, manual, remat))))(stacked)
        np.testing.assert_allclose(got[0], want[0], rtol=1e-6)
        for seed in range(3):
            assert_trees_close(jax.tree.map(lambda leaf, s=seed: leaf[s], got[1]),
                               jax.tree.map(lambda leaf, s=seed: leaf[s], want[1]))
