"""Whether a run folder's checkpoints can be continued by this code with a given configuration.

Three checks, all before anything is compiled: the run's saved :class:`TrainConfig` must equal the new one except
for settings that do not change the computation (:data:`RESUMABLE_CHANGES`); the agent's resolved
hyperparameters must equal the saved ones (the code's defaults may have changed since the run); and the
training state's layout (tree structure, shapes, dtypes) must be what this code builds.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re

import jax

from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, TrainConfig, incompatibilities
from lnnmpc.train.loop import TrainingLoop


def state_signature(loop: TrainingLoop, seeds: int) -> str:
    """A hash of the training state's layout (tree structure, shapes, dtypes): traced, not compiled."""
    shapes = jax.eval_shape(jax.vmap(loop.init), jax.random.split(jax.random.key(0), seeds))
    leaves, treedef = jax.tree_util.tree_flatten(shapes)
    structure = re.sub(r" at 0x[0-9a-f]+", "", str(treedef))  # object addresses differ between processes
    text = structure + "".join(f"{x.shape}{x.dtype}" for x in leaves)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def check_layout(run: str, signature: str) -> None:
    """Refuses checkpoints whose state layout differs from what this code builds (:func:`state_signature`)."""
    if runfolder.read_config(run).get("state_signature") != signature:
        raise ConfigError(f"the checkpoints in {run} hold a training state of another layout than this code "
                          "builds for the same configuration (the code changed since the run); start a new run")


def agent_config_json(agent_config) -> dict:
    """The agent's resolved hyperparameters as config.json stores them."""
    return json.loads(json.dumps(jsonable(agent_config), default=str))


def check_agent_config(run: str, agent_config) -> None:
    """Refuses to resume when the agent's resolved hyperparameters differ from the checkpoint's (e.g. the code's
    defaults changed since the run): the continuation would no longer be the same training."""
    saved = _flatten(runfolder.read_config(run).get("agent_config") or {})
    current = _flatten(agent_config_json(agent_config))
    changed = [f"{k}: checkpoint has {saved.get(k)!r}, now {current.get(k)!r}"
               for k in sorted(saved.keys() | current.keys()) if saved.get(k) != current.get(k)]
    if changed:
        raise ConfigError(f"cannot resume {run}: the agent's hyperparameters differ from the checkpoint's "
                          f"({'; '.join(changed)}): the code's defaults or the --set overrides changed since the run. "
                          "Restore them with --set KEY=VALUE (e.g. --set planner.horizon=3) or start a new run")


def _flatten(tree: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def check_compatible(run: str, saved: TrainConfig, config: TrainConfig) -> None:
    """Refuses a configuration that differs from the saved one in more than :data:`RESUMABLE_CHANGES`."""
    problems = incompatibilities(saved, config)
    if problems:
        raise ConfigError(f"cannot resume {run} with a changed configuration ({'; '.join(problems)}). Only "
                          "steps, checkpoint_every, keep_checkpoints, devices, name, runs_dir, tensorboard, "
                          "wandb, compile_cache and overrides that keep the agent's hyperparameters may change; "
                          "start a new run for anything else")


def jsonable(value):
    """A dataclass as a dict (other values unchanged), for JSON."""
    return dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
