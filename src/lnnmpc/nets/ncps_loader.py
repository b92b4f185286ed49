"""Convert ncps (torch, 1.0.1) ``CfC``/``CfCCell``/``LTC``/``LTCCell`` state dicts into lnnmpc cell variables.

Usage::

    state_dict = {k: v.detach().cpu().numpy() for k, v in torch_model.state_dict().items()}
    variables = load_ncps_state_dict(CfCCell(hidden_size=64), state_dict)   # {'params': ...}
    new_h, out = CfCCell(hidden_size=64).apply(variables, h, x, dt)

Wrapper keys (``rnn_cell.`` prefix) and bare-cell keys are both accepted. Not supported (``ValueError``):
mixed memory (``lstm.*``), output projections (``fc.*``), wired CfC cells (``sparsity_mask``) and LTC
wirings other than fully connected (masks that are not all ones). The result is checked against the cell's
own parameter tree (names and shapes), so a state dict of another configuration is rejected instead of
being silently misread.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.nets.cfc import CfCCell
from lnnmpc.nets.ltc import LTCCell

WRAPPER_PREFIX = "rnn_cell."
UNSUPPORTED_PREFIXES = {"lstm.": "mixed_memory=True", "fc.": "a proj_size output projection"}
CFC_HEADS = ("ff1", "ff2", "time_a", "time_b")
LTC_MASKS = ("sparsity_mask", "sensory_sparsity_mask")


def load_ncps_state_dict(cell: CfCCell | LTCCell, state_dict: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``{'params': ...}`` for ``cell`` holding the weights of an ncps torch module.

    ``state_dict`` maps ncps parameter names to arrays (numpy arrays, or anything ``numpy.asarray`` accepts,
    e.g. detached CPU tensors). Torch ``Linear`` weights (out, in) become Flax kernels (in, out).
    """
    arrays = _strip_wrapper_prefix(state_dict)
    if isinstance(cell, CfCCell):
        params, input_size = _cfc_params(cell, arrays)
    elif isinstance(cell, LTCCell):
        params, input_size = _ltc_params(cell, arrays)
    else:
        raise ValueError(f"cell of type {type(cell).__name__!r} is not supported; allowed: CfCCell, LTCCell")
    params = jax.tree.map(lambda value: jnp.asarray(value, dtype=cell.param_dtype), params)
    _check_against_cell(cell, params, input_size)
    return {"params": params}


def _to_numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def _strip_wrapper_prefix(state_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
    arrays = {}
    for key, value in state_dict.items():
        for prefix, feature in UNSUPPORTED_PREFIXES.items():
            if key.startswith(prefix):
                raise ValueError(f"state dict key {key!r} comes from {feature}, which is not supported")
        arrays[key.removeprefix(WRAPPER_PREFIX)] = _to_numpy(value)
    return arrays


def _pop_linear(arrays: dict[str, np.ndarray], torch_name: str) -> dict[str, np.ndarray]:
    """Remove ``{torch_name}.weight/.bias`` from ``arrays`` and return a Flax Dense dict (kernel = W.T)."""
    try:
        weight, bias = arrays.pop(f"{torch_name}.weight"), arrays.pop(f"{torch_name}.bias")
    except KeyError as missing:
        raise ValueError(f"state dict lacks {missing.args[0]!r}") from None
    return {"kernel": weight.T, "bias": bias}


def _cfc_params(cell: CfCCell, arrays: dict[str, np.ndarray]) -> tuple[dict[str, Any], int]:
    arrays = dict(arrays)
    if "sparsity_mask" in arrays:
        raise ValueError("state dict has 'sparsity_mask' (a wired CfC cell), which is not supported")
    # Backbone Linear layers sit at Sequential indices 0, 2, 4|5, ... (dropout shifts them): order by index.
    matches = (re.fullmatch(r"backbone\.(\d+)\.weight", key) for key in arrays)
    indices = sorted(int(match.group(1)) for match in matches if match)
    if len(indices) != cell.backbone_layers:
        raise ValueError(f"state dict has {len(indices)} backbone layers, cell has "
                         f"backbone_layers={cell.backbone_layers}")
    params: dict[str, Any] = {f"backbone_{layer}": _pop_linear(arrays, f"backbone.{index}")
                              for layer, index in enumerate(indices)}
    heads = CFC_HEADS[:1] if cell.mode == "pure" else CFC_HEADS
    params.update({head: _pop_linear(arrays, head) for head in heads})
    if cell.mode == "pure":
        for name in ("w_tau", "A"):
            if name not in arrays:
                raise ValueError(f"state dict lacks {name!r}, which mode='pure' needs")
            params[name] = arrays.pop(name)
    if arrays:
        raise ValueError(f"state dict has keys {sorted(arrays)} that a CfCCell(mode={cell.mode!r}, "
                         f"backbone_layers={cell.backbone_layers}) does not use")
    first = params["backbone_0"] if cell.backbone_layers > 0 else params["ff1"]
    return params, first["kernel"].shape[0] - cell.hidden_size


def _ltc_params(cell: LTCCell, arrays: dict[str, np.ndarray]) -> tuple[dict[str, Any], int]:
    arrays = dict(arrays)
    for mask in LTC_MASKS:
        if mask in arrays and not np.all(arrays.pop(mask) == 1):
            raise ValueError(f"state dict has a {mask!r} that is not all ones: only the FullyConnected "
                             f"wiring is supported")
    if "sensory_w" not in arrays:
        raise ValueError("state dict lacks 'sensory_w': not an ncps LTC state dict")
    return arrays, arrays["sensory_w"].shape[0]


def _check_against_cell(cell: CfCCell | LTCCell, params: dict[str, Any], input_size: int) -> None:
    """Raise ``ValueError`` unless ``params`` has exactly the names and shapes ``cell.init`` would create."""
    if input_size < 1:
        raise ValueError(f"state dict implies input size {input_size}; does hidden_size={cell.hidden_size} "
                         f"match the torch module?")
    state, inputs, dt = jnp.zeros((1, cell.hidden_size)), jnp.zeros((1, input_size)), jnp.ones((1, 1))
    expected = jax.eval_shape(cell.init, jax.random.PRNGKey(0), state, inputs, dt)["params"]
    expected_shapes = {jax.tree_util.keystr(path): leaf.shape
                       for path, leaf in jax.tree_util.tree_leaves_with_path(expected)}
    given_shapes = {jax.tree_util.keystr(path): leaf.shape
                    for path, leaf in jax.tree_util.tree_leaves_with_path(params)}
    if expected_shapes != given_shapes:
        mismatched = sorted(k for k in expected_shapes.keys() | given_shapes.keys()
                            if expected_shapes.get(k) != given_shapes.get(k))
        details = ", ".join(f"{k}: state dict {given_shapes.get(k)} vs cell {expected_shapes.get(k)}"
                            for k in mismatched)
        raise ValueError(f"state dict does not fit {cell!r}: {details}")
