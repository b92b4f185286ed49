"""Checkpoints of the whole training state (agent, optimisers, replay buffer, environments, RNG) with orbax.

A checkpoint is ``<run>/checkpoints/<env_step>/`` written by an orbax ``CheckpointManager`` (orbax writes into a
temporary folder and renames it when complete, so a run killed mid-save leaves the previous checkpoint intact),
plus the host's counters in the same step (JSON). Typed PRNG keys are stored as their raw key data and
re-wrapped on restore. ``latest_step`` finds the newest complete checkpoint.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp


def _is_key(x: Any) -> bool:
    return isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key)


def _to_raw(tree: Any) -> Any:
    return jax.tree_util.tree_map(lambda x: jax.random.key_data(x) if _is_key(x) else x, tree)


def _from_raw(raw: Any, like: Any) -> Any:
    return jax.tree_util.tree_map(lambda r, x: jax.random.wrap_key_data(r) if _is_key(x) else r, raw, like)


def _payload(tree: Any) -> dict:
    """Non-empty leaves by flat index (orbax cannot store zero-size arrays, which mjx.Data has)."""
    return {str(i): leaf for i, leaf in enumerate(jax.tree_util.tree_leaves(tree)) if leaf.size > 0}


def _unpayload(payload: dict, like: Any) -> Any:
    leaves, treedef = jax.tree_util.tree_flatten(like)
    return jax.tree_util.tree_unflatten(treedef, [payload.get(str(i), leaf) for i, leaf in enumerate(leaves)])


def _manager(run: str, keep: int = 2) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True)
    return ocp.CheckpointManager(os.path.abspath(os.path.join(run, "checkpoints")), options=options)


def save_checkpoint(run: str, step: int, state: Any, host: dict) -> None:
    """Saves ``state`` (any pytree of arrays, PRNG keys allowed) and ``host`` (JSON-able) as checkpoint ``step``."""
    with _manager(run) as manager:
        manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(_payload(_to_raw(state))),
                                                   host=ocp.args.JsonSave(host)))
        manager.wait_until_finished()


def latest_step(run: str) -> int | None:
    """Newest complete checkpoint step in ``run``, or None."""
    if not os.path.isdir(os.path.join(run, "checkpoints")):
        return None
    with _manager(run) as manager:
        return manager.latest_step()


def restore_checkpoint(run: str, step: int, like: Any) -> tuple[Any, dict]:
    """Restores checkpoint ``step`` into the structure, shapes and dtypes of ``like``; returns (state, host)."""
    raw_like = _to_raw(like)
    abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, _payload(raw_like))
    with _manager(run) as manager:
        restored = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                                 host=ocp.args.JsonRestore()))
    return _from_raw(_unpayload(dict(restored["state"]), raw_like), like), dict(restored["host"])
