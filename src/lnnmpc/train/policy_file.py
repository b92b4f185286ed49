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

With ``eval_policies`` (``train --eval-policies``) the trainer also keeps the policy of every evaluation, in the same
format, as ``<run>/policies/policy-<env step>.npz`` (a 1-seed acrobot policy: ~2.4 MB): a run back from a GPU can
then be evaluated and analysed at each evaluation's step (e.g. before and after a dip), not only at its last.
"""

from __future__ import annotations

import dataclasses
import os
import re
from typing import Any

import jax
import numpy as np

from lnnmpc.train.config import ConfigError

POLICY_FILE = "policy.npz"
SNAPSHOT_DIR = "policies"  # the policy of each evaluation, with eval_policies
_SNAPSHOT = re.compile(r"policy-(\d+)[.]npz")
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
    return _write_policy(os.path.join(run, POLICY_FILE), step, agent_state)


def save_policy_snapshot(run: str, step: int, agent_state: Any) -> str:
    """Writes the same as :func:`save_policy` to ``<run>/policies/policy-<step>.npz`` (kept beside the others);
    returns its path."""
    os.makedirs(os.path.join(run, SNAPSHOT_DIR), exist_ok=True)
    return _write_policy(snapshot_path(run, step), step, agent_state)


def _write_policy(path: str, step: int, agent_state: Any) -> str:
    paths, leaves, _ = _paths_and_leaves(_exported(agent_state))
    arrays = {f"leaf_{i}": np.asarray(leaf) for i, leaf in enumerate(leaves)}
    temporary = f"{path}.tmp-{os.getpid()}"
    with open(temporary, "wb") as f:
        np.savez(f, step=np.int64(step), paths=np.asarray(paths), **arrays)
    os.replace(temporary, path)
    return path


def snapshot_path(run: str, step: int) -> str:
    """Where the policy of the evaluation at environment step ``step`` is kept: ``<run>/policies/policy-<step>.npz``."""
    return os.path.join(run, SNAPSHOT_DIR, f"policy-{int(step)}.npz")


def snapshot_steps(run: str) -> list[int]:
    """The environment steps of ``<run>/policies/policy-<step>.npz`` files, ascending (empty without any)."""
    folder = os.path.join(run, SNAPSHOT_DIR)
    if not os.path.isdir(folder):
        return []
    return sorted(int(m.group(1)) for m in map(_SNAPSHOT.fullmatch, os.listdir(folder)) if m)


def policy_path(run: str, step: int) -> str | None:
    """The file holding ``run``'s policy at environment step ``step``: ``policy.npz`` where it is of that step,
    else that step's evaluation snapshot; None where neither exists."""
    if policy_step(run) == step:
        return os.path.join(run, POLICY_FILE)
    path = snapshot_path(run, step)
    return path if os.path.isfile(path) else None


def policy_step(run: str) -> int | None:
    """The environment step of ``<run>/policy.npz``, or None without one."""
    path = os.path.join(run, POLICY_FILE)
    if not os.path.isfile(path):
        return None
    with np.load(path) as archive:
        return int(archive["step"])


def restore_policy(run: str, like: Any, path: str | None = None) -> Any:
    """``like`` (an agent state of the run's configuration, seed-batched, e.g. freshly initialised) with the
    ``params``, ``scale`` and ``updates`` of ``<run>/policy.npz`` (or of the file ``path``, e.g. a snapshot of
    :func:`policy_path`), each leaf placed as ``like``'s; a file whose leaves differ from ``like``'s (another agent
    or size) raises a ConfigError naming the first that differs."""
    path = path or os.path.join(run, POLICY_FILE)
    if not os.path.isfile(path):
        raise ConfigError(f"{run!r} has no {os.path.relpath(path, run)}")
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
