"""The environment: pure ``reset`` / ``step`` / ``reset_to`` over an :class:`EnvState` pytree.

    env = make("walker-run", obs_noise=0.1)
    state = jax.jit(env.reset)(jax.random.key(0))
    state = jax.jit(env.step)(state, jnp.zeros(env.action_size))

Batch with ``jax.vmap`` (environments, or seeds × environments with two vmaps). ``step`` never resets by itself;
``state.done`` marks the time limit (truncation: dm_control never terminates these tasks early).
"""

from __future__ import annotations

import contextlib
import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from lnnmpc.envs import physics as phys
from lnnmpc.envs.corruptions import (
    CorruptionConfig,
    CorruptionState,
    corruption_reset,
    corruption_step,
    kept_indices,
)
from lnnmpc.envs.solver import unrolled_solver
from lnnmpc.envs.tasks import TASKS, TaskSpec, model_ids


@struct.dataclass
class EnvState:
    """State of one environment (add leading axes with ``vmap``).

    Attributes:
      physics: the MJX physics state (``mjx.Data``), kinematics in sync with qpos/qvel.
      obs: (obs_dim,) the observation the agent receives (after every corruption).
      reward: () reward of the last agent step (summed over the action repeat); 0 after reset.
      done: () bool, the episode's time limit is reached.
      dt: () agent steps between the capture times of the previous and this delivered observation.
      t: () int32 agent steps since reset.
      key: PRNG key for the corruptions.
      clean_obs: (full_obs_dim,) uncorrupted dm_control observation of the current physics state.
      corruption: the corruption pipeline's state.
    """

    physics: mjx.Data
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    dt: jax.Array
    t: jax.Array
    key: jax.Array
    clean_obs: jax.Array
    corruption: CorruptionState


@dataclasses.dataclass(frozen=True, eq=False)
class Env:
    """A dm_control task on MJX with an observation-corruption pipeline. Build with :func:`make`."""

    spec: TaskSpec
    action_repeat: int
    physics_options: phys.PhysicsOptions
    corruption: CorruptionConfig
    mj_model: mujoco.MjModel
    mjx_model: mjx.Model
    ids: dict
    joints: dict
    kept: np.ndarray
    n_substeps: int

    # ------------------------------------------------------------------------------------- shapes
    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def action_size(self) -> int:
        return int(self.mj_model.nu)

    @property
    def observation_size(self) -> int:
        return int(self.kept.size)

    @property
    def agent_timestep(self) -> float:
        """Simulated seconds per agent step: the physics timestep x its substeps per control step x action repeat."""
        return float(self.mj_model.opt.timestep * self.n_substeps) * self.action_repeat

    @property
    def episode_length(self) -> int:
        """Agent steps per episode (control steps / action repeat, rounded up)."""
        return -(-self.spec.control_steps // self.action_repeat)

    # -------------------------------------------------------------------------------- internals
    def _solver_context(self):
        return unrolled_solver() if self.physics_options.unrolled_solver else contextlib.nullcontext()

    def _clean_obs(self, data: mjx.Data) -> jax.Array:
        return jnp.concatenate([value for _, value in self.spec.observe(data, self.ids)])

    def _start(self, data: mjx.Data, key: jax.Array) -> EnvState:
        clean = self._clean_obs(data)
        cstate, obs, dt = corruption_reset(self.corruption, key, clean[self.kept])
        zero = jnp.zeros((), clean.dtype)
        return EnvState(
            physics=data, obs=obs, reward=zero, done=jnp.zeros((), bool), dt=dt,
            t=jnp.zeros((), jnp.int32), key=jax.random.fold_in(key, 1), clean_obs=clean, corruption=cstate,
        )

    # ---------------------------------------------------------------------------------- public
    def initial_qpos_qvel(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Samples dm_control's initial-state distribution: (qpos (nq,), qvel (nv,))."""
        return self.spec.init(key, self.joints, self.mj_model.nq, self.mj_model.nv)

    def reset_start(self, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """What an episode begun with ``key`` starts from, by :meth:`reset` and by a restart of
        :meth:`step_or_reset`: (qpos (nq,), qvel (nv,)) drawn by :meth:`initial_qpos_qvel` from the key's first
        half, and the second half, which seeds the corruptions."""
        k_init, k_obs = jax.random.split(key)
        qpos, qvel = self.initial_qpos_qvel(k_init)
        return qpos, qvel, k_obs

    def reset(self, key: jax.Array) -> EnvState:
        """Starts an episode from dm_control's initial-state distribution (one jitted program per environment and
        argument shapes: :func:`_traced_once`)."""
        return _jitted_reset(self, key)

    def _reset(self, key: jax.Array) -> EnvState:
        return self.reset_to(*self.reset_start(key))

    def reset_to(self, qpos: jax.Array, qvel: jax.Array, key: jax.Array | None = None) -> EnvState:
        """Starts an episode at a given physics state (qpos (nq,), qvel (nv,)); ``key`` seeds corruptions."""
        nq, nv = self.mj_model.nq, self.mj_model.nv
        if jnp.shape(qpos)[-1:] != (nq,) or jnp.shape(qvel)[-1:] != (nv,):
            raise ValueError(
                f"{self.name}: qpos/qvel must have shapes ({nq},) and ({nv},), "
                f"got {jnp.shape(qpos)} and {jnp.shape(qvel)}"
            )
        key = jax.random.key(0) if key is None else key
        with self._solver_context():
            data = phys.data_from_state(self.mjx_model, qpos, qvel)
        return self._start(data, key)

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Applies ``action`` (action_size,) for ``action_repeat`` control steps; rewards are summed (one jitted
        program per environment and argument shapes: :func:`_traced_once`)."""
        return _jitted_step(self, state, action)

    def _step(self, state: EnvState, action: jax.Array) -> EnvState:
        action = self._checked_action(action)
        data, rewards = self._control_steps(state.physics, action)
        return self._stepped(state, data, rewards)

    def step_or_reset(self, state: EnvState, action: jax.Array, restart: jax.Array, key: jax.Array) -> EnvState:
        """``step(state, action)`` where ``restart`` (bool scalar) is False, ``reset(key)`` where it is True, with
        one forward-dynamics program for both (:func:`physics.control_step` with ``restart``): the training loop,
        which may restart any environment at any step, compiles the physics once instead of a step and a reset.
        One jitted program per environment and argument shapes (:func:`_traced_once`)."""
        return _jitted_step_or_reset(self, state, action, restart, key)

    def _step_or_reset(self, state: EnvState, action: jax.Array, restart: jax.Array, key: jax.Array) -> EnvState:
        action = self._checked_action(action)
        qpos, qvel, k_obs = self.reset_start(key)
        fresh = phys.fresh_data(self.mjx_model, qpos, qvel)
        data, rewards = self._control_steps(state.physics, action, restart, fresh)
        return phys.select(restart, self._start(data, k_obs), self._stepped(state, data, rewards))

    def _control_steps(self, physics, action: jax.Array, restart=None, fresh=None):
        """``action_repeat`` control steps from ``physics`` (:func:`physics.control_step`): (data, rewards)."""
        def control(data, _):
            data = phys.control_step(self.mjx_model, data, action, self.n_substeps,
                                     self.spec.needs_velocity_sensors, restart, fresh)
            return data, self.spec.reward(data, action, self.ids)

        with self._solver_context():
            return jax.lax.scan(control, physics, None, length=self.action_repeat)

    def _checked_action(self, action: jax.Array) -> jax.Array:
        action = jnp.asarray(action)
        if action.shape != (self.action_size,):
            raise ValueError(
                f"{self.name}: action must have shape ({self.action_size},), got {action.shape} "
                "(use jax.vmap for batches)"
            )
        return action

    def _stepped(self, state: EnvState, data, rewards: jax.Array) -> EnvState:
        """The state after a step that ended at ``data`` with ``rewards`` (action_repeat,)."""
        t = state.t + 1
        clean = self._clean_obs(data)
        key, k_obs = jax.random.split(state.key)
        cstate, obs, dt = corruption_step(self.corruption, state.corruption, k_obs, t, clean[self.kept])
        return EnvState(
            physics=data, obs=obs, reward=jnp.sum(rewards).astype(clean.dtype),
            done=t * self.action_repeat >= self.spec.control_steps, dt=dt, t=t, key=key,
            clean_obs=clean, corruption=cstate,
        )


def _traced_once(method):
    """``method`` (an :class:`Env` method) jitted with the environment static (hashed by identity: ``eq=False``).

    JAX then traces an environment's physics once per argument shapes and process, and reuses that trace, and its
    ``vmap``-ed form, in every program that calls it: the trainer's seed and training chunks and its evaluation
    hold the same step. Tracing MJX is the costly part of building those programs (a cartpole training chunk
    traced and lowered in 9.9 s with the step inlined, 4.7 s after the seed chunk had traced the jitted step; a
    second seed chunk 6.2 s -> 0.7 s; 2-core CPU). XLA inlines the nested call when it compiles, so the compiled
    programs do the same work. Called outside a trace, the method runs compiled instead of op by op."""
    return jax.jit(method, static_argnums=0)


_jitted_reset = _traced_once(Env._reset)
_jitted_step = _traced_once(Env._step)
_jitted_step_or_reset = _traced_once(Env._step_or_reset)


def make(task: str, *, physics: str | phys.PhysicsOptions = "fast", action_repeat: int = 2, **obs_options) -> Env:
    """Builds an environment.

    Args:
      task: one of :data:`TASKS` (e.g. "walker-run", "cartpole-swingup-sparse").
      physics: "fast" (training default), "exact" (dm_control's solver), or a :class:`PhysicsOptions`.
      action_repeat: control steps per agent step (>= 1); rewards are summed over them.
      **obs_options: ``remove_vel``, ``obs_noise``, ``flicker``, ``delay`` (see :mod:`lnnmpc.envs.corruptions`).
    """
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; known: {', '.join(TASKS)}")
    if isinstance(action_repeat, bool) or not isinstance(action_repeat, int | np.integer) or action_repeat < 1:
        raise ValueError(f"action_repeat must be an integer >= 1, got {action_repeat!r}")
    spec = TASKS[task]
    options = phys.resolve_profile(physics, spec.domain)
    corruption = CorruptionConfig.from_options(obs_options)
    model = phys.load_model(spec.domain, options)
    n_substeps = spec.n_substeps
    if options.timestep is not None:
        default_dt = phys.load_model(spec.domain, phys.PhysicsOptions()).opt.timestep
        n_substeps = phys.substeps_per_control_step(spec.n_substeps, default_dt, options.timestep)
    return Env(
        spec=spec, action_repeat=int(action_repeat), physics_options=options, corruption=corruption,
        mj_model=model, mjx_model=phys.put_model(model), ids=model_ids(spec.domain, model),
        joints=phys.joint_info(model), kept=kept_indices(spec.obs_keys, corruption), n_substeps=n_substeps,
    )
