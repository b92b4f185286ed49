"""The trained policy beside the checkpoints: ``<run>/policy.npz``, the agent's parameters alone.

A checkpoint holds the whole training state, most of it the replay buffer (a walker seed at 200K steps: ~48 MB of
its ~68 MB), so a run trained on a lent GPU comes back without it. ``policy.npz`` holds what acting needs, the
agent state's ``params`` (plus its Q ``scale`` and update count), for every seed: ~3.7 MB per walker seed with
the 512-wide SimNorm head. The trainer rewrites it with each checkpoint, so it is the newest checkpoint's policy;
:func:`lnnmpc.train.evaluate.load_policy` (``eval``, ``video``, the analyses) falls back to it when a run has no
checkpoint at that step, with the optimiser states and target Q heads, which acting never reads, freshly
initialised.

The file is a plain NumPy archive (``numpy.load`` reads it without lnnmpc): ``step`` (environment steps), ``paths``
(each leaf's key path, e.g. ``['params']['encoder']['Dense_0']['kernel']``) and ``leaf_<i>`` (the i-th leaf,
(seeds, ...)). It is written under a temporary name and renamed, so a run killed mid-write keeps the previous one.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import numpy as np

from lnnmpc.train.config import ConfigError

POLICY_FILE = "policy.npz"
EXPORTED = ("params", "scale", "updates")  # the AgentState fields the file holds


def _exported(agent_state: Any) -> dict:
    return {name: getattr(agent_state, name) for name in EXPORTED}


def _paths_and_leaves(tree: Any) -> tuple[list[str], list[Any], Any]:
    """Each leaf's key path (as text), the leaves and the tree's structure."""
    flat, treedef = jax.tree_util.tree_flatten_with_path(tree)
    return [jax.tree_util.keystr(path) for path, _ in flat], [leaf for _, leaf in flat], treedef


def save_policy(run: str, step: int, agent_state: Any) -> str:
    """Writes ``agent_state``'s ``params``, ``scale`` and ``updates`` (seed-batched) as ``<run>/policy.npz`` at
    environment step ``step`` (replacing the previous file atomically); returns its path."""
    paths, leaves, _ = _paths_and_leaves(_exported(agent_state))
    arrays = {f"leaf_{i}": np.asarray(leaf) for i, leaf in enumerate(leaves)}
    path = os.path.join(run, POLICY_FILE)
    temporary = f"{path}.tmp-{os.getpid()}"
    with open(temporary, "wb") as f:
        np.savez(f, step=np.int64(step), paths=np.asarray(paths), **arrays)
    os.replace(temporary, path)
    return path


def policy_step(run: str) -> int | None:
    """The environment step of ``<run>/policy.npz``, or None without one."""
    path = os.path.join(run, POLICY_FILE)
    if not os.path.isfile(path):
        return None
    with np.load(path) as archive:
        return int(archive["step"])


def restore_policy(run: str, like: Any) -> Any:
    """``like`` (an agent state of the run's configuration, seed-batched, e.g. freshly initialised) with the
    ``params``, ``scale`` and ``updates`` of ``<run>/policy.npz``, each leaf placed as ``like``'s; a file whose
    leaves differ from ``like``'s (another agent or size) raises a ConfigError naming the first that differs."""
    path = os.path.join(run, POLICY_FILE)
    if not os.path.isfile(path):
        raise ConfigError(f"{run!r} has no {POLICY_FILE}")
    like_paths, like_leaves, treedef = _paths_and_leaves(_exported(like))
    with np.load(path) as archive:
        paths = [str(p) for p in archive["paths"]]
        if paths != like_paths:
            extra, missing = sorted(set(paths) - set(like_paths)), sorted(set(like_paths) - set(paths))
            raise ConfigError(f"{path} does not fit the run's agent: leaves only in the file {extra[:3]}, "
                              f"only in the agent {missing[:3]}")
        leaves = []
        for i, (name, want) in enumerate(zip(paths, like_leaves, strict=True)):
            got = archive[f"leaf_{i}"]
            if got.shape != want.shape or got.dtype != want.dtype:
                raise ConfigError(f"{path}: {name} is {got.dtype}{list(got.shape)}, the run's agent has "
                                  f"{want.dtype}{list(want.shape)}")
            leaves.append(jax.device_put(got, want.sharding) if isinstance(want, jax.Array) else got)
    return dataclasses.replace(like, **jax.tree_util.tree_unflatten(treedef, leaves))
