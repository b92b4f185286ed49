"""What a training run is set up from: :func:`validate` checks a configuration (or a run folder to resume)
completely without compiling anything and returns the :class:`Setup` (environments, agent and loop built, the
run folder checked, a checkpoint to resume from checked against the configuration and the state's layout);
:func:`build_loop` builds environments, agent and loop (the environments shared in the process: :func:`shared_env`);
:func:`enable_compile_cache` turns on XLA's persistent compilation cache. :mod:`lnnmpc.train.trainer` runs what
this sets up.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any

import jax

from lnnmpc import envs
from lnnmpc.agents.registry import make_agent, task_default_overrides
from lnnmpc.replay import replay_capacity_for
from lnnmpc.train import runfolder, schedule
from lnnmpc.train.checkpoint import latest_step
from lnnmpc.train.compat import check_agent_config, check_compatible, check_layout, layout_signature, state_shapes
from lnnmpc.train.config import ConfigError, TrainConfig
from lnnmpc.train.loop import LoopConfig, TrainingLoop, windows_after_seed_phase
from lnnmpc.train.provenance import mark_startup
from lnnmpc.train.sharding import device_count_for

MAX_CHUNK = 1000  # iterations per compiled training chunk


@dataclasses.dataclass(frozen=True)
class Setup:
    """What a validated configuration builds (nothing compiled yet)."""

    config: TrainConfig
    loop: TrainingLoop
    run: str
    resume_step: int | None
    num_devices: int
    state_shapes: Any  # the training state's ShapeDtypeStructs (compat.state_shapes), traced once

    @property
    def signature(self) -> str:
        """The state layout's hash (:func:`compat.layout_signature`), as config.json records it."""
        return layout_signature(self.state_shapes)

    @property
    def per_iteration(self) -> int:
        """Environment steps of one loop iteration (all environments of a seed, action repeat included)."""
        return self.config.envs * self.loop.env.action_repeat

    @property
    def seed_iterations(self) -> int:
        """Loop iterations of the random seed phase."""
        return schedule.seed_iterations(self.config.seed_steps, self.per_iteration)

    @property
    def burst_updates(self) -> int:
        """Updates of the burst after the seed phase: as many per seed-phase iteration as a training iteration
        makes (``LoopConfig.updates_per_iteration``)."""
        return self.seed_iterations * self.loop.config.updates_per_iteration

    @property
    def chunk(self) -> int:
        """Iterations per training chunk (:func:`schedule.chunk_length`: equal chunks that end the run at its
        budget). Fixed by the configuration, so a resumed run with the same budget chunks identically."""
        c = self.config
        return schedule.chunk_length(c.steps, self.seed_iterations, self.per_iteration, self.loop.env.episode_length,
                                     c.eval_every, MAX_CHUNK)

    @property
    def final_env_steps(self) -> int:
        """Environment steps per seed at which the run ends (the first chunk boundary at or past ``steps``)."""
        return schedule.final_steps(self.config.steps, self.seed_iterations, self.chunk, self.per_iteration,
                                    self.loop.env.episode_length)


def shared_env(task: str, physics: str, options: dict) -> envs.Env:
    """``envs.make(task, physics=physics, **options)``, one Env per argument set in this process (the newest 16).

    An Env's jitted physics is traced once per Env object (env.py, ``_traced_once``), so every loop, evaluation
    and video of equal options in one process (``build_loop`` for a run and for its evaluation, ``validate``
    of several agents on one task) reuses one trace instead of tracing the physics anew (~2-3 s each on a CPU).
    An Env is immutable; the key holds ``jax_enable_x64``, under which the model's arrays are built (float64)."""
    key = tuple((name, type(value).__name__, value) for name, value in sorted(options.items()))
    try:
        hash(key)
    except TypeError:  # an option value that cannot be hashed: an Env of its own
        return envs.make(task, physics=physics, **options)
    return _cached_env(task, physics, key, bool(jax.config.jax_enable_x64))


@functools.lru_cache(maxsize=16)
def _cached_env(task: str, physics: str, options: tuple, x64: bool) -> envs.Env:
    """:func:`shared_env`'s Envs, keyed by its arguments (``options``: (name, type name, value), sorted)."""
    return envs.make(task, physics=physics, **{name: value for name, _, value in options})


def config_env(config: TrainConfig, options: dict) -> envs.Env:
    """The configuration's task Env with corruption ``options`` (:func:`shared_env`): its physics profile and
    action repeat (given to ``envs.make`` only where it departs from make's default, so that Envs of the default
    stay one per process with those built without it)."""
    repeat = {} if config.action_repeat == 2 else {"action_repeat": config.action_repeat}
    return shared_env(config.task, config.physics, {**options, **repeat})


def build_loop(config: TrainConfig) -> TrainingLoop:
    """Environments (:func:`shared_env`), agent and loop of a configuration (ValueErrors become ConfigErrors)."""
    try:
        env = config_env(config, config.obs)
        eval_env = config_env(config, config.eval_obs)  # equal options: the training Env
        if eval_env.observation_size != env.observation_size:
            raise ConfigError(f"eval_obs {config.eval_obs} changes the observation size "
                              f"({env.observation_size} -> {eval_env.observation_size}); remove_vel must match")
        agent = make_agent(config.agent, env.observation_size, env.action_size, model_size=config.model_size,
                           small=config.small, overrides=config.overrides or None)
    except ConfigError:
        raise
    except ValueError as error:
        raise ConfigError(str(error)) from None
    capacity = config.replay_capacity or (
        replay_capacity_for(config.steps, env.action_repeat, config.envs) + 2 * (env.episode_length + 1))
    if capacity < agent.sequence_length + 1:
        raise ConfigError(f"replay_capacity={capacity} is below the training window ({agent.sequence_length})")
    seeded = schedule.seed_iterations(config.seed_steps, config.envs * env.action_repeat)
    guard = not windows_after_seed_phase(seeded, env.episode_length, agent.sequence_length, capacity)
    loop_config = LoopConfig(num_envs=config.envs, batch_size=config.batch_size, replay_capacity=capacity,
                             eval_episodes=config.eval_episodes, guard_empty_replay=guard,
                             eval_prior=config.eval_prior, explore_noise_beta=config.explore_noise_beta,
                             seed_noise_beta=config.seed_noise_beta, updates_per_step=config.updates_per_step)
    try:
        return TrainingLoop(agent, env, eval_env, loop_config)
    except ValueError as error:  # eval_prior with an agent that has no policy prior
        raise ConfigError(f"eval_prior: {error}") from None


def validate(config: TrainConfig | None = None, *, resume: str | None = None, steps: int | None = None,
             create: bool = True) -> Setup:
    """Checks everything that can be checked without compiling; returns the :class:`Setup` to train with.

    ``resume``: a run folder to continue (its config.json is used; ``config``, if also given, must be
    compatible); ``steps`` extends the budget. A ``config.out`` folder that holds checkpoints is resumed too.
    ``create=False`` (``train --check``) writes nothing: a new run folder is only checked to be creatable.
    """
    mark_startup("imports")
    if config is None and resume is None:
        raise ConfigError("give a TrainConfig or a run folder to resume")
    changes = {} if steps is None else {"steps": steps}
    config = dataclasses.replace(config or runfolder.saved_config(resume), **changes)
    if resume is not None:
        config = dataclasses.replace(config, out=resume)
    run = runfolder.new_run_path(config)
    if os.path.exists(os.path.join(run, runfolder.CONFIG_FILE)):
        saved = runfolder.saved_config(run)
        if config.replay_capacity is None:  # the buffer keeps its size when a resumed run gets more steps
            config = dataclasses.replace(config, replay_capacity=saved.replay_capacity)
        # what the run recorded (task defaults included) holds unless the user sets it again
        config = dataclasses.replace(config, overrides={**saved.overrides, **config.overrides})
        check_compatible(run, saved, config)
    elif resume is not None:
        raise ConfigError(f"{resume!r} is not a run folder (no {runfolder.CONFIG_FILE})")
    else:  # a new run records its task's default hyperparameters with the user's overrides
        config = dataclasses.replace(config, overrides=task_default_overrides(config.agent, config.task,
                                                                              config.overrides))
    enable_deterministic_ops(config.deterministic)
    jax.devices()  # the backend's start (GPU contexts), timed on its own
    mark_startup("devices")
    loop = build_loop(config)
    mark_startup("built")
    config = dataclasses.replace(config, replay_capacity=loop.config.replay_capacity)
    if create:
        runfolder.ensure_writable(run)
    else:
        runfolder.check_creatable(run)
    if config.tensorboard:
        try:
            import tensorboardX  # noqa: F401
        except ImportError:
            raise ConfigError("tensorboard=True needs the tensorboardX package (pip install tensorboardX)") from None
    if config.wandb:
        try:
            import wandb  # noqa: F401
        except ImportError:
            raise ConfigError(f"wandb={config.wandb!r} needs the wandb package (pip install wandb)") from None
    num_devices = device_count_for(config.seeds, jax.device_count(), config.devices)
    resume_step = latest_step(run) if os.path.isdir(run) else None
    shapes = state_shapes(loop, config.seeds)
    if resume_step is not None:
        check_layout(run, layout_signature(shapes))
        check_agent_config(run, loop.agent.config)
    mark_startup("validated")
    return Setup(config=config, loop=loop, run=run, resume_step=resume_step, num_devices=num_devices,
                 state_shapes=shapes)


DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def enable_deterministic_ops(on: bool) -> None:
    """Adds :data:`DETERMINISTIC_FLAG` to ``XLA_FLAGS`` (``TrainConfig.deterministic``). XLA reads the variable
    once, when JAX starts its backend: where this process started a GPU backend already without the flag, raises
    ConfigError, since the run would silently not be deterministic. A started CPU backend is left as it is (its
    programs replay anyway), as is a variable that already holds the flag."""
    if not on:
        return
    flags = os.environ.get("XLA_FLAGS", "")
    if DETERMINISTIC_FLAG in flags.split():
        return
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        if jax.default_backend() == "cpu":
            return
        raise ConfigError(f"deterministic=True needs XLA_FLAGS={DETERMINISTIC_FLAG} before JAX starts its "
                          f"{jax.default_backend()} backend, and this process started it already (XLA_FLAGS="
                          f"{flags!r}): set the variable before the first JAX computation, or train from the "
                          "command line (--deterministic)")
    os.environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_FLAG}".strip()


def enable_compile_cache(folder: str) -> None:
    """XLA's persistent compilation cache in ``folder`` (a resumed run or an evaluation then skips compiling)."""
    if folder:
        os.makedirs(folder, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
