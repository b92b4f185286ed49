"""The trainer's configuration: one frozen, validated dataclass that the CLI, the Makefile and the Python API share.

``TrainConfig(task="walker-run", seeds=4, obs="noise=0.1,flicker=0.2")`` checks every value that can be checked
without building anything (types, ranges, names); :func:`lnnmpc.train.setup.validate` then builds the
environments and the agent (still without compiling) so that unknown corruption options or agent overrides fail
before minutes of compilation. Errors are :class:`ConfigError` (a ``ValueError``) naming the bad value and the
allowed ones.

Observation corruptions are given as text (``"noise=0.1,flicker=0.2,delay=3,remove_vel=1"``) or as a dict of
:func:`lnnmpc.envs.make` options; they are stored resolved (``{"obs_noise": 0.1, "flicker": 0.2}``).
"""

from __future__ import annotations

import dataclasses
import os
import re
import sys
from collections.abc import Callable, Mapping
from typing import Any

from lnnmpc import envs

OBS_KEYS = {"noise": "obs_noise", "obs_noise": "obs_noise", "flicker": "flicker", "delay": "delay",
            "remove_vel": "remove_vel"}
TRUE, FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")

# Settings a run may change when it is resumed; everything else must equal the checkpoint's configuration.
# ``eval_prior`` adds episodes to the evaluations and changes nothing of the training or the planner's returns;
# ``eval_policies`` only writes files.
# ``overrides`` may change as long as the agent's resolved hyperparameters stay those of the checkpoint (checked
# by lnnmpc.train.compat.check_agent_config), e.g. to pin a default that changed in the code since the run.
# ``deterministic`` changes only how a GPU sums (round-off), not what is computed; each start records its XLA_FLAGS.
RESUMABLE_CHANGES = ("steps", "name", "runs_dir", "checkpoint_every", "keep_checkpoints", "devices",
                     "tensorboard", "wandb", "compile_cache", "compile_ahead", "eval_prior", "eval_policies",
                     "overrides", "deterministic")
COMPILE_AHEAD = ("auto", "on", "off")


BACKENDS = ("mjx", "dm_control")  # evaluation backends: MJX on the device, dm_control's simulator on the CPU


class ConfigError(ValueError):
    """A configuration value is invalid (the message names it and the allowed values)."""


def command_status(action: Callable[[], str], errors: tuple[type[Exception], ...] = (ConfigError,)) -> int:
    """Exit status of a command-line tool's ``action``: 0 after writing the text it returns to stdout, 2 after
    writing ``error: <message>`` to stderr when it raises one of ``errors`` (input named by its message)."""
    try:
        text = action()
    except errors as error:
        sys.stderr.write(f"error: {error}\n")
        return 2
    sys.stdout.write(f"{text}\n")
    return 0


def _obs_value(name: str, value: str) -> Any:
    if name == "remove_vel":
        if value.lower() not in TRUE + FALSE:
            raise ConfigError(f"remove_vel={value!r}: use one of {', '.join(TRUE + FALSE)}")
        return value.lower() in TRUE
    try:
        return int(value) if name == "delay" else float(value)
    except ValueError:
        kind = "an integer" if name == "delay" else "a number"
        raise ConfigError(f"{name}={value!r} is not {kind}") from None


def parse_obs(text: str | Mapping | None) -> dict:
    """``"noise=0.1,flicker=0.2,delay=3,remove_vel=1"`` (or a dict of make() options) -> make() options."""
    if isinstance(text, Mapping):
        items = [(k, v) for k, v in text.items()]
    else:
        items = []
        for item in filter(None, (part.strip() for part in (text or "").split(","))):
            key, sep, value = item.partition("=")
            if not sep:
                raise ConfigError(f"bad observation option {item!r}; use key=value with keys {', '.join(OBS_KEYS)}")
            items.append((key.strip(), value.strip()))
    options = {}
    for key, value in items:
        if key not in OBS_KEYS:
            raise ConfigError(f"bad observation option {key!r}; known: {', '.join(OBS_KEYS)}")
        name = OBS_KEYS[key]
        options[name] = _obs_value(name, value) if isinstance(value, str) else value
    try:
        envs.CorruptionConfig.from_options(options)
    except ValueError as error:
        raise ConfigError(f"observation options {options}: {error}") from None
    return options


def obs_tag(options: Mapping) -> str:
    """A short folder-name tag for corruption options: ``noise0.1-flicker0.2`` or ``clean``."""
    names = {"obs_noise": "noise", "flicker": "flicker", "delay": "delay", "remove_vel": "novel"}
    parts = [names[k] if v is True else f"{names[k]}{v:g}" for k, v in sorted(options.items()) if v]
    return "-".join(parts) or "clean"


def parse_overrides(items: list[str] | Mapping | None, option: str = "--set") -> dict:
    """``["planner.horizon=5", "lr=1e-3"]`` -> ``{"planner.horizon": 5, "lr": 0.001}`` (JSON-ish values);
    ``option`` names the command-line option in the error for an item without ``=``."""
    if isinstance(items, Mapping):
        return dict(items)
    import json

    overrides = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"bad {option} {item!r}; use KEY=VALUE, e.g. {option} "
                              f"{'lr=1e-3' if option == '--set' else 'iterations=12'}")
        try:
            overrides[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key.strip()] = value  # plain strings need no quotes
    return overrides


def default_compile_cache() -> str:
    """Where compiled XLA programs are kept between processes (a resumed run or ``make eval`` skips compiling)."""
    return os.environ.get("LNNMPC_COMPILE_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "lnnmpc", "xla"))


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (SPEC §1, §5). Units: environment steps (dm_control steps).

    Attributes:
      task, agent: names from ``lnnmpc.envs.TASKS`` and ``lnnmpc.agents.registry.AGENTS``.
      seeds: independent seeds trained together (``vmap``; sharded over devices when there are several).
      steps: environment steps per seed. seed_steps: random-action steps first (then one update per agent step).
      envs: environments per seed. obs / eval_obs: corruption options for training / evaluation (eval_obs None:
        same as obs).
      eval_every, eval_episodes: evaluation cadence and episodes per seed.
      eval_prior: every evaluation also plays its episodes (the same initial states and keys) with the policy
        prior acting alone (``lnnmpc.agents.actor``), in the same compiled program; eval.csv gains a
        ``prior_return`` column. Off: the evaluation and eval.csv are those of runs before the option. A resumed
        run may turn it on or off (the training does not depend on it).
      eval_policies: every evaluation also writes the policy it evaluated (parameters alone, as ``policy.npz``) to
        ``policies/policy-<env step>.npz`` (:mod:`lnnmpc.train.policy_file`), so that ``eval``, ``video`` and the
        analyses can replay any evaluation's policy of a run whose checkpoints stayed on the GPU.
      explore_noise_beta: None (TD-MPC2): the planner's exploration noise in training is white, drawn anew at
        every step; β >= 0: each environment draws, at every episode start, one Gaussian sequence over the episode
        with power spectrum 1/f^β (1: pink, 2: red; ``lnnmpc.agents.exploration``), and step t's sample replaces
        the white draw (still times the planner's std). Evaluation never explores.
      seed_noise_beta: None (TD-MPC2): the seed phase acts uniformly at random in [-1, 1]; β >= 0: it acts with
        one such colored sequence per environment and episode (unit std, clipped to [-1, 1]). On
        cartpole-swingup-sparse uniform actions never reach the reward, pink ones in 29% of episodes
        (``experiments/results/random-exploration-sparse-cpu``), so the replay holds rewarded steps before
        the first update. An episode running when the seed phase ends keeps its sequence as its exploration noise
        (when ``explore_noise_beta`` is set).
      updates_per_step: updates per agent step, the update-to-data ratio (1: TD-MPC2's, one update per agent
        step). k > 1 makes k updates per agent step of every environment, and k per seed-phase agent step in the
        burst after the seed phase: k times the learning per environment step at k times the update cost. Updates
        are counted per seed (the agent's ``lr_decay_begin`` / ``lr_decay_end`` are in updates, so they come k
        times sooner in environment steps).
      action_repeat: control steps per agent step (2, TD-MPC2's on dm_control; ``lnnmpc.envs.make``): the agent
        acts every ``action_repeat`` x the task's control timestep and the rewards in between are summed, so an
        episode has 1000 / action_repeat agent steps; environment steps (``steps``, ``seed_steps``,
        ``eval_every``) count control steps either way, while updates and the agent's horizons count agent steps.
      checkpoint_every, keep_checkpoints: checkpoint cadence (also at the end and on Ctrl-C) and how many to keep.
      model_size, small, batch_size, physics, replay_capacity, overrides: agent/loop settings; ``overrides`` goes
        to ``make_agent(..., overrides=...)`` (keys as the agent defines them).
      seed: master seed. devices: devices to shard seeds over (None: as many as divide ``seeds``).
      runs_dir, name, out: the run folder is ``out`` or ``<runs_dir>/<task>/<agent>/<timestamp>-<name>``
        (name defaults to the corruption tag, e.g. ``noise0.1-flicker0.2`` or ``clean``).
      tensorboard: also write TensorBoard scalars (needs the ``tensorboardX`` package).
      wandb: a Weights & Biases project to log to ("" = off; needs the ``wandb`` package; ``WANDB_MODE=offline``
        logs without network).
      compile_cache: folder for XLA's persistent compilation cache ("" turns it off).
      compile_ahead: compile the run's programs in parallel threads before the first runs ("on"), or each
        when first called ("off"); "auto": on with at least 4 CPU cores (with fewer, threads gain little and a
        run stopped early pays for programs it never called).
      deterministic: compile under XLA's deterministic GPU ops (``--xla_gpu_deterministic_ops=true`` added to
        ``XLA_FLAGS`` before the backend starts). Without it, two launches of one command on a GPU may part by
        round-off (RESULTS.md [92]: apart at their first evaluation); with it, two side by side on an H100 wrote
        the same eval.csv and train.csv bit for bit (RESULTS.md [93]), at 302-304 env steps/s each against
        [91]'s 399 without (acrobot recipe, another H100). No effect on the CPU, whose launches replay anyway.
    """

    task: str
    agent: str = "tdmpc2"
    seeds: int = 1
    steps: int = 200_000
    envs: int = 1
    obs: Any = dataclasses.field(default_factory=dict)
    eval_obs: Any = None
    model_size: int = 5
    seed_steps: int = 5000
    eval_every: int = 10_000
    eval_episodes: int = 10
    checkpoint_every: int = 10_000
    keep_checkpoints: int = 3
    batch_size: int = 256
    updates_per_step: int = 1
    action_repeat: int = 2
    physics: str = "fast"
    seed: int = 0
    small: bool = False
    replay_capacity: int | None = None
    overrides: Any = dataclasses.field(default_factory=dict)
    devices: int | None = None
    runs_dir: str = "runs"
    name: str = ""
    out: str | None = None
    tensorboard: bool = False
    wandb: str = ""
    compile_cache: str = dataclasses.field(default_factory=default_compile_cache)
    compile_ahead: str = "auto"
    eval_prior: bool = False
    eval_policies: bool = False
    explore_noise_beta: float | None = None
    seed_noise_beta: float | None = None
    deterministic: bool = False

    def __post_init__(self):
        from lnnmpc.agents.registry import AGENTS

        if self.task not in envs.TASKS:
            raise ConfigError(f"unknown task {self.task!r}; known: {', '.join(envs.TASKS)}")
        if self.agent not in AGENTS:
            raise ConfigError(f"unknown agent {self.agent!r}; known: {', '.join(AGENTS)}")
        if self.physics not in envs.PROFILES:
            raise ConfigError(f"unknown physics profile {self.physics!r}; known: {', '.join(envs.PROFILES)}")
        if self.model_size not in (1, 5):
            raise ConfigError(f"model_size must be 1 or 5 (million parameters), got {self.model_size!r}")
        for name in ("seeds", "steps", "envs", "eval_every", "eval_episodes", "checkpoint_every",
                     "keep_checkpoints", "batch_size", "updates_per_step", "action_repeat"):
            require_int(name, getattr(self, name), 1)
        require_int("seed_steps", self.seed_steps, 0)
        require_int("seed", self.seed, 0)
        for name in ("replay_capacity", "devices"):
            if getattr(self, name) is not None:
                require_int(name, getattr(self, name), 1)
        if self.steps < self.seed_steps:
            raise ConfigError(f"steps ({self.steps}) must be >= seed_steps ({self.seed_steps}): the budget "
                              "includes the random seed phase")
        for name in ("small", "tensorboard", "eval_prior", "eval_policies", "deterministic"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be True or False, got {getattr(self, name)!r}")
        for name, default in (("explore_noise_beta", "TD-MPC2's white noise"),
                              ("seed_noise_beta", "uniform random actions")):
            beta = getattr(self, name)
            if beta is not None and (isinstance(beta, bool) or not isinstance(beta, (int, float))
                                     or not 0 <= beta <= 4):
                raise ConfigError(f"{name} must be a number in [0, 4] (0 white, 1 pink, 2 red) or None ({default}), "
                                  f"got {beta!r}")
        if not isinstance(self.wandb, str) or not re.fullmatch(r"[A-Za-z0-9._-]{0,128}", self.wandb):
            raise ConfigError(f"wandb project {self.wandb!r} must be letters, digits, '.', '_' or '-' (at most 128; "
                              "empty turns W&B logging off)")
        if self.compile_ahead not in COMPILE_AHEAD:
            raise ConfigError(f"compile_ahead={self.compile_ahead!r}; allowed: {', '.join(COMPILE_AHEAD)}")
        if "/" in self.name or self.name.startswith("."):
            raise ConfigError(f"run name {self.name!r} must not contain '/' or start with '.'")
        obs = parse_obs(self.obs)
        object.__setattr__(self, "obs", obs)
        object.__setattr__(self, "eval_obs", obs if self.eval_obs is None else parse_obs(self.eval_obs))
        object.__setattr__(self, "overrides", parse_overrides(self.overrides))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping, **changes) -> TrainConfig:
        """Rebuilds a config from ``to_dict()`` output (unknown keys are refused), with ``changes`` applied."""
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - fields)
        if unknown:
            raise ConfigError(f"unknown configuration key(s) {unknown}; known: {', '.join(sorted(fields))}")
        return cls(**{**values, **changes})

    def resumable_part(self) -> dict:
        """The settings a resumed run must share with its checkpoint."""
        return {k: v for k, v in self.to_dict().items() if k not in RESUMABLE_CHANGES + ("out",)}


def require_int(name: str, value: Any, minimum: int) -> None:
    """Raise ConfigError unless ``value`` is an integer >= ``minimum`` (bools are rejected)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")


def incompatibilities(saved: TrainConfig, current: TrainConfig) -> list[str]:
    """Human-readable differences that forbid resuming ``saved`` with ``current`` (empty: compatible)."""
    a, b = saved.resumable_part(), current.resumable_part()
    return [f"{k}: checkpoint has {a.get(k)!r}, now {b.get(k)!r}" for k in sorted(a.keys() | b.keys())
            if a.get(k) != b.get(k)]
