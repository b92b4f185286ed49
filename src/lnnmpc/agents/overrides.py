"""Hyperparameter overrides by field name for nested frozen agent configs (``--set KEY=VALUE``).

An agent config is a frozen dataclass whose fields are scalars or nested frozen dataclasses (``model``,
``planner``). Every scalar field, at the top or one level down, is addressed by its bare name; a few nested
names are renamed (:data:`RENAMED`: the planner's ``horizon`` is ``plan_horizon``, distinct from the training
``horizon``) and a few are tied to a top-level field of the same name (:data:`TIED`: one ``gamma`` for the
value targets and the planner). The explicit ``section.field`` spelling (``planner.horizon``, ``model.num_q``)
addresses exactly that one field. ``obs_dim`` / ``action_dim`` come from the environment and are not overridable.
Values are converted to the type of the field's current value (strings from a command line included), and the
configs' own validation runs on the result.
"""

from __future__ import annotations

import dataclasses
from typing import Any

RENAMED = {("planner", "horizon"): "plan_horizon"}
TIED = {("planner", "gamma")}
FIXED = {"obs_dim", "action_dim"}
_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def override_paths(config: Any) -> dict[str, list[tuple[str, ...]]]:
    """Every overridable key of ``config`` and the field paths it sets (``("planner", "horizon")``, ...)."""
    paths: dict[str, list[tuple[str, ...]]] = {}
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if not dataclasses.is_dataclass(value):
            paths.setdefault(field.name, []).append((field.name,))
            continue
        for sub in dataclasses.fields(value):
            path = (field.name, sub.name)
            if sub.name in FIXED or dataclasses.is_dataclass(getattr(value, sub.name)):
                continue
            key = RENAMED.get(path, sub.name)
            if key in paths and path not in TIED:
                raise AssertionError(f"override key {key!r} is ambiguous: {paths[key]} and {path}")
            paths.setdefault(key, []).append(path)
    return paths


def convert(key: str, value: Any, like: Any) -> Any:
    """``value`` (a number, bool or string) as the type of ``like``; ValueError names the key and the value."""
    kind = type(like)
    try:
        if kind is bool:
            text = str(value).strip().lower()
            if text not in _TRUE + _FALSE:
                raise ValueError
            return text in _TRUE
        if kind is int:
            number = float(value)
            if isinstance(value, bool) or not number.is_integer():
                raise ValueError
            return int(number)
        if kind is float:
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        if kind is str:
            return str(value)
    except (TypeError, ValueError):
        pass
    else:
        raise ValueError(f"{key} cannot be overridden (its value {like!r} is not a number, bool or string)")
    raise ValueError(f"{key}={value!r} is not a valid {kind.__name__}")


def apply_overrides(config: Any, overrides: dict[str, Any] | None) -> Any:
    """``config`` with ``overrides`` ({key: value}) applied; ValueError on an unknown key lists the allowed ones."""
    if not overrides:
        return config
    paths = override_paths(config)
    paths.update({".".join(path): [path] for targets in list(paths.values()) for path in targets if len(path) == 2})
    unknown = sorted(set(overrides) - set(paths))
    if unknown:
        bare = sorted(key for key in paths if "." not in key)
        raise ValueError(f"unknown hyperparameter {', '.join(map(repr, unknown))}; allowed: {', '.join(bare)} "
                         f"(or section.field, e.g. planner.horizon)")
    top: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for key, value in overrides.items():
        for path in paths[key]:
            holder = config if len(path) == 1 else getattr(config, path[0])
            converted = convert(key, value, getattr(holder, path[-1]))
            if len(path) == 1:
                top[path[0]] = converted
            else:
                nested.setdefault(path[0], {})[path[1]] = converted
    for name, changes in nested.items():
        try:
            top[name] = dataclasses.replace(getattr(config, name), **changes)
        except ValueError as error:  # the section names its own field (planner: horizon); say which --set it was
            keys = [key for key in overrides if any(path[0] == name and len(path) == 2 for path in paths[key])]
            given = ", ".join(f"{key}={overrides[key]!r}" for key in keys)
            raise ValueError(f"{name}: {error} (set by {given})") from error
    return dataclasses.replace(config, **top)


def planner_keys(config: Any) -> list[str]:
    """The override keys of ``config`` that set only its planner (``plan_horizon``, ``iterations``, ...): what an
    evaluation may change without changing the trained model (``gamma`` is tied to the value targets: not one)."""
    return sorted(key for key, paths in override_paths(config).items() if all(path[0] == "planner" for path in paths))


def apply_planner_overrides(config: Any, planner: dict[str, Any] | None) -> Any:
    """``config`` with planner-only ``planner`` overrides applied (bare keys of :func:`planner_keys` or
    ``planner.FIELD``); ValueError on any other key lists the allowed ones (the model, losses and optimisers must
    stay those the parameters were trained with)."""
    if not planner:
        return config
    allowed = planner_keys(config)
    wrong = sorted(key for key in planner if key not in allowed and not key.startswith("planner."))
    if wrong:
        raise ValueError(f"{', '.join(map(repr, wrong))} is not a planner setting; an evaluation may change only: "
                         f"{', '.join(allowed)} (or planner.FIELD)")
    return apply_overrides(config, planner)
