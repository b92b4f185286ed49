"""Parity of lnnmpc's CfC/LTC cells with ncps 1.0.1 (torch), through committed fixtures and the loader."""

from __future__ import annotations

import json
from pathlib import Path

import flax.linen
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.nets import CfCCell, LTCCell, fully_connected_polarities, load_ncps_state_dict, unroll

FIXTURES = sorted((Path(__file__).parent / "fixtures").glob("ncps_*.npz"))
CELL_CLASSES = {"CfCCell": CfCCell, "LTCCell": LTCCell}
TOLERANCE = 1e-5


def load_fixture(path: Path) -> tuple[dict, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Return (config, state_dict, arrays) of one fixture file."""
    with np.load(path) as data:
        arrays = {key: data[key] for key in data.files}
    config = json.loads(str(arrays.pop("config")))
    param_keys = [key for key in arrays if key.startswith("param:")]
    state_dict = {key.removeprefix("param:"): arrays.pop(key) for key in param_keys}
    return config, state_dict, arrays


def test_fixture_set_covers_every_mode_and_cell():
    configs = [load_fixture(path)[0] for path in FIXTURES]
    cfc = [c for c in configs if c["cell"] == "CfCCell"]
    assert {c["kwargs"]["mode"] for c in cfc} == {"default", "no_gate", "pure"}
    assert any(c["kwargs"]["backbone_layers"] >= 2 for c in cfc)
    assert {c["kwargs"]["backbone_activation"] for c in cfc} - {"lecun_tanh"}
    ltc = [c for c in configs if c["cell"] == "LTCCell"]
    assert {c["kwargs"]["implicit_param_constraints"] for c in ltc} == {True, False}
    assert {c["protocol"] for c in configs} == {"cell_steps", "wrapper"}
    assert sum(path.stat().st_size for path in FIXTURES) < 500_000


@pytest.mark.parametrize("path", FIXTURES, ids=[p.stem for p in FIXTURES])
def test_matches_ncps(path: Path):
    config, state_dict, arrays = load_fixture(path)
    cell = CELL_CLASSES[config["cell"]](**config["kwargs"])
    variables = load_ncps_state_dict(cell, state_dict)
    assert arrays["inputs"].shape[0] >= 16
    if config["protocol"] == "cell_steps":
        assert np.any(arrays["dts"] == 0) and arrays["dts"].max() > 4.0
        assert np.unique(arrays["dts"][0]).size > 1  # per-sample Δt within a step
    result = unroll(cell, variables, jnp.asarray(arrays["initial_state"]), jnp.asarray(arrays["inputs"]),
                    jnp.asarray(arrays["dts"]))
    assert result.states.dtype == jnp.float32
    state_error = float(jnp.max(jnp.abs(result.states - arrays["states"])))
    output_error = float(jnp.max(jnp.abs(result.outputs - arrays["outputs"])))
    assert state_error <= TOLERANCE, state_error
    assert output_error <= TOLERANCE, output_error


def test_fully_connected_polarities_match_ncps():
    _, _, arrays = load_fixture(next(p for p in FIXTURES if p.stem == "ncps_ltc_implicit"))
    hidden, inputs = arrays["init_erev"].shape[0], arrays["init_sensory_erev"].shape[0]
    erev, sensory_erev = fully_connected_polarities(hidden, inputs)
    np.testing.assert_array_equal(erev, arrays["init_erev"])
    np.testing.assert_array_equal(sensory_erev, arrays["init_sensory_erev"])
    cell = LTCCell(hidden)
    variables = cell.init(jax.random.PRNGKey(0), jnp.zeros((1, hidden)), jnp.zeros((1, inputs)))
    np.testing.assert_array_equal(variables["params"]["erev"], arrays["init_erev"])


def cfc_default_state_dict() -> dict[str, np.ndarray]:
    return load_fixture(next(p for p in FIXTURES if p.stem == "ncps_cfc_default"))[1]


@pytest.mark.parametrize(
    ("cell", "edit", "message"),
    [
        (CfCCell(8, backbone_units=16, backbone_layers=2), None, "backbone_layers=2"),
        (CfCCell(8, backbone_units=16, mode="pure"), None, "w_tau"),
        (CfCCell(6, backbone_units=16), None, "ff1"),
        (CfCCell(8, backbone_units=32), None, "backbone_0"),
        (CfCCell(8, backbone_units=16), ("lstm.input_map.weight", np.zeros((32, 5))), "mixed_memory"),
        (CfCCell(8, backbone_units=16), ("fc.weight", np.zeros((3, 8))), "proj_size"),
        (CfCCell(8, backbone_units=16), ("sparsity_mask", np.ones((8, 13))), "sparsity_mask"),
        (CfCCell(8, backbone_units=16), ("extra", np.ones(3)), "extra"),
        (LTCCell(8), None, "sensory_w"),
    ],
)
def test_loader_rejects_mismatched_state_dicts(cell, edit, message):
    state_dict = cfc_default_state_dict()
    if edit is not None:
        state_dict[edit[0]] = edit[1]
    with pytest.raises(ValueError, match=message):
        load_ncps_state_dict(cell, state_dict)


def test_loader_rejects_sparse_ltc_wiring():
    _, state_dict, _ = load_fixture(next(p for p in FIXTURES if p.stem == "ncps_ltc_implicit"))
    state_dict["sparsity_mask"] = np.eye(8, dtype=np.float32)
    with pytest.raises(ValueError, match="sparsity_mask"):
        load_ncps_state_dict(LTCCell(8), state_dict)
    state_dict.pop("sparsity_mask")
    with pytest.raises(ValueError, match="output_b"):
        load_ncps_state_dict(LTCCell(8, output_mapping="linear"), state_dict)


def test_loader_rejects_unknown_cell_type():
    with pytest.raises(ValueError, match="'Dense'.*CfCCell, LTCCell"):
        load_ncps_state_dict(flax.linen.Dense(3), {})
