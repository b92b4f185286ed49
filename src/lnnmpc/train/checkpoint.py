"""Checkpoints of the whole training state (agent, optimisers, replay buffer, environments, RNG) with orbax.

A checkpoint is ``<run>/checkpoints/<env_step>/`` written by an orbax ``CheckpointManager`` (orbax writes into a
temporary folder and renames it when complete, so a run killed mid-save leaves the previous checkpoint intact),
plus the host's counters in the same step (JSON). Typed PRNG keys are stored as their raw key data and
re-wrapped on restore. ``latest_step`` finds the newest complete checkpoint; an interrupted write (a leftover
``<step>.orbax-checkpoint-tmp-*`` folder) is never listed. The newest ``keep`` checkpoints are kept. Arrays are
restored with the shardings of the ``like`` tree, so a run can resume on another number of devices.
"""

from __future__ import annotations

import math
import os
from typing import Any

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp


def _is_key(x: Any) -> bool:
    return isinstance(x, jax.Array | jax.ShapeDtypeStruct) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key)


def keys_as_data(tree: Any) -> Any:
    """``tree`` with every typed PRNG key replaced by its raw key data (uint32), as checkpoints store keys; other
    leaves as they are."""
    return jax.tree_util.tree_map(lambda x: jax.random.key_data(x) if _is_key(x) else x, tree)


def _raw_abstract(x: Any) -> Any:
    """A restore target's leaf (array or abstract) as :func:`keys_as_data` stores it: for a key, its data's shape and
    dtype with the key's sharding; any other leaf as it is."""
    if not _is_key(x):
        return x
    data = jax.eval_shape(jax.random.key_data, x)
    return jax.ShapeDtypeStruct(data.shape, data.dtype, sharding=x.sharding)


def _abstract(x: Any) -> jax.ShapeDtypeStruct:
    """Shape, dtype and sharding to restore a leaf into (abstract leaves go to the default device)."""
    if not isinstance(x, jax.ShapeDtypeStruct):
        return ocp.utils.to_shape_dtype_struct(x)
    sharding = x.sharding or jax.sharding.SingleDeviceSharding(jax.devices()[0])
    return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)


def _from_raw(raw: Any, like: Any) -> Any:
    return jax.tree_util.tree_map(lambda r, x: jax.random.wrap_key_data(r) if _is_key(x) else r, raw, like)


def _payload(tree: Any) -> dict:
    """Non-empty leaves by flat index (orbax cannot store zero-size arrays, which mjx.Data has)."""
    return {str(i): leaf for i, leaf in enumerate(jax.tree_util.tree_leaves(tree)) if math.prod(leaf.shape) > 0}


def _unpayload(payload: dict, like: Any) -> Any:
    leaves, treedef = jax.tree_util.tree_flatten(like)
    empty = lambda leaf: leaf if isinstance(leaf, jax.Array) else jax.device_put(jnp.zeros(leaf.shape, leaf.dtype),
                                                                                  leaf.sharding)
    return jax.tree_util.tree_unflatten(treedef, [payload[str(i)] if str(i) in payload else empty(leaf)
                                                  for i, leaf in enumerate(leaves)])


def _manager(run: str, keep: int | None = None) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True)
    return ocp.CheckpointManager(os.path.abspath(os.path.join(run, "checkpoints")), options=options)


def save_checkpoint(run: str, step: int, state: Any, host: dict, keep: int = 2) -> None:
    """Saves ``state`` (any pytree of arrays, PRNG keys allowed) and ``host`` (JSON-able) as checkpoint ``step``;
    keeps the newest ``keep`` checkpoints."""
    with _manager(run, keep) as manager:
        manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(_payload(keys_as_data(state))),
                                                   host=ocp.args.JsonSave(host)))
        manager.wait_until_finished()


def latest_step(run: str) -> int | None:
    """Newest complete checkpoint step in ``run``, or None."""
    if not os.path.isdir(os.path.join(run, "checkpoints")):
        return None
    with _manager(run) as manager:
        return manager.latest_step()


def all_steps(run: str) -> list[int]:
    """Steps of all complete checkpoints in ``run``, oldest first."""
    if not os.path.isdir(os.path.join(run, "checkpoints")):
        return []
    with _manager(run) as manager:
        return sorted(manager.all_steps())


def restore_checkpoint(run: str, step: int, like: Any) -> tuple[Any, dict]:
    """Restores checkpoint ``step`` into the structure, shapes, dtypes (and shardings) of ``like``, a pytree of
    arrays or of ``jax.ShapeDtypeStruct`` (e.g. from ``jax.eval_shape``); returns (state, host)."""
    raw_like = jax.tree_util.tree_map(_raw_abstract, like)
    abstract = jax.tree_util.tree_map(_abstract, _payload(raw_like))
    with _manager(run) as manager:
        restored = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                                 host=ocp.args.JsonRestore()))
    return _from_raw(_unpayload(dict(restored["state"]), raw_like), like), dict(restored["host"])
