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
from lnnmpc.train.config import RESUMABLE_CHANGES, ConfigError, TrainConfig, incompatibilities
from lnnmpc.train.loop import TrainingLoop


def state_shapes(loop: TrainingLoop, seeds: int):
    """The training state of ``seeds`` seeds as ``jax.ShapeDtypeStruct`` leaves: traced, not run or compiled."""
    return jax.eval_shape(jax.vmap(loop.init), jax.random.split(jax.random.key(0), seeds))


def state_signature(loop: TrainingLoop, seeds: int) -> str:
    """A hash of the training state's layout (tree structure, shapes, dtypes): traced, not compiled."""
    return layout_signature(state_shapes(loop, seeds))


def layout_signature(shapes) -> str:
    """:func:`state_signature` of the state's :func:`state_shapes`."""
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


# Agent fields added after runs existed, with the value that computes what the code did before: a checkpoint whose
# saved agent configuration lacks the field resumes when the field has that value now.
ADDED_AGENT_FIELDS = {"nll_beta": 0.0, "model.input_transform": "none", "joint_grad_clip": False,
                      "model.simnorm_layer_norm": False, "flat_optimizer": False, "rollout_steps": 1,
                      "scan_unroll": 1, "rollout_stride": 1, "model.latent_head": "none", "model.simnorm_dim": 8,
                      "model.latent_size": 0, "model.latent_obs_skip": False,
                      "model.latent_head_hidden": 0, "learn_episode_starts": False,
                      "planner.explore_min_std": 0.0, "planner.terminal_q": "mean", "lr_decay_begin": 0,
                      "lr_decay_end": 0, "lr_final_scale": 1.0, "target_q": "min"}


def check_agent_config(run: str, agent_config) -> None:
    """Refuses to resume when the agent's resolved hyperparameters differ from the checkpoint's (e.g. the code's
    defaults changed since the run): the continuation would no longer be the same training. Fields the agent does
    not use (``agent_config.inactive_fields()``, e.g. free bits of a det variant) are not compared; a field the
    checkpoint predates (:data:`ADDED_AGENT_FIELDS`) must hold its old behaviour's value. The error names the
    ``--set`` flags that restore the checkpoint's values."""
    current = agent_config_json(agent_config)
    inactive = agent_config.inactive_fields() if hasattr(agent_config, "inactive_fields") else set()
    changes = agent_config_changes(runfolder.read_config(run).get("agent_config") or {}, current, inactive)
    changed = [f"{key}: checkpoint has {was!r}, now {now!r}" for key, was, now in changes]
    current_keys = flatten_config(current).keys()
    restore = [f"--set {key}={was}" for key, was, _ in changes if was is not None and key in current_keys]
    if changed:
        how = f"Restore them with {' '.join(restore)}" if restore else "Restore them with --set KEY=VALUE"
        raise ConfigError(f"cannot resume {run}: the agent's hyperparameters differ from the checkpoint's "
                          f"({'; '.join(changed)}): the code's defaults or the --set overrides changed since the run. "
                          f"{how} or start a new run")


def agent_config_changes(a: dict, b: dict, inactive: set[str] | frozenset[str] = frozenset()) -> list[tuple]:
    """(key, value in ``a``, value in ``b``) for every flattened agent setting (``model.latent_size``) on which two
    ``agent_config`` JSONs differ, keys in ``inactive`` skipped; a field one of them predates takes its old
    behaviour's value from :data:`ADDED_AGENT_FIELDS` (None for any other missing field)."""
    flat_a, flat_b = flatten_config(a), flatten_config(b)
    changes = []
    for key in sorted(flat_a.keys() | flat_b.keys()):
        if key in inactive:
            continue
        was = flat_a[key] if key in flat_a else ADDED_AGENT_FIELDS.get(key)
        now = flat_b[key] if key in flat_b else ADDED_AGENT_FIELDS.get(key)
        if was != now:
            changes.append((key, was, now))
    return changes


def flatten_config(tree: dict, prefix: str = "") -> dict:
    """A nested config dict as one level with dotted keys (``{"model": {"mlp_dim": 192}}`` -> ``model.mlp_dim``)."""
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(flatten_config(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def check_compatible(run: str, saved: TrainConfig, config: TrainConfig) -> None:
    """Refuses a configuration that differs from the saved one in more than :data:`RESUMABLE_CHANGES`."""
    problems = incompatibilities(saved, config)
    if problems:
        changeable = ", ".join(name for name in RESUMABLE_CHANGES if name != "overrides")
        raise ConfigError(f"cannot resume {run} with a changed configuration ({'; '.join(problems)}). Only "
                          f"{changeable} and overrides that keep the agent's hyperparameters may change; start a "
                          "new run for anything else")


def jsonable(value):
    """A dataclass as a dict (other values unchanged), for JSON."""
    return dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
