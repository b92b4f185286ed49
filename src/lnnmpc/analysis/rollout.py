"""Deterministic episodes of a trained agent, recording what the representation analyses need (JAX).

:func:`rollout` plays ``episodes`` episodes of one seed's agent on an environment (the evaluation protocol:
MPPI without exploration noise) and returns, per episode and agent step t (arrays (E, T, ...)):

* ``latent``: the agent's latent after reading o_t (LNN agents: the encoder state h_t = z_t from the acting
  carry; ``tdmpc2``: its encoder applied to o_t);
* ``obs`` (the delivered, corrupted observation), ``clean_obs`` (dm_control's uncorrupted observation of the
  current physics state), ``qpos``, ``qvel`` (true physical state), ``action`` a_t, ``dt``, ``reward``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.agents.registry import acting_latent
from lnnmpc.train.evaluate import SameProgram
from lnnmpc.train.loop import play_episodes
from lnnmpc.train.step_report import report_step, reporting


def rollout_program(agent, env, episodes: int, steps: int | None = None):
    """The compiled ``(state, key) -> records`` of :func:`rollout` (time-major leaves (T, E, ...)); the agent
    state is an argument, so one compilation serves every checkpoint of a run, and an agent of the same class and
    configuration on an equal environment (another policy object of the same run) reuses it too. The episodes are
    the trainer's evaluation's (:func:`lnnmpc.train.loop.play_episodes`): the same key plays the same episodes."""
    return _rollout_program(SameProgram(agent, env), episodes, steps)


@functools.lru_cache(maxsize=8)
def _rollout_program(pair: SameProgram, episodes: int, steps: int | None):
    agent, env = pair.agent, pair.env

    def episodes_from(state, key):  # reset and scan in one compiled program (eager MJX resets are slow)
        def record(s, carry, action, nxt):
            return {"latent": acting_latent(agent, state, carry, s.obs), "obs": s.obs, "clean_obs": s.clean_obs,
                    "qpos": s.physics.qpos, "qvel": s.physics.qvel, "action": action, "dt": s.dt,
                    "reward": nxt.reward}

        return play_episodes(agent, state, env, key, episodes, steps, record, on_step=report_step)[1]

    return jax.jit(episodes_from)


rollout_program.cache_info = _rollout_program.cache_info


def rollout(agent, state, env, key: jax.Array, episodes: int, steps: int | None = None,
            progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """Records of ``episodes`` deterministic episodes (module docstring); ``state``: one seed's agent state;
    ``steps``: agent steps per episode (default the whole episode); ``progress(done, total)`` is called as the
    agent steps of the (parallel) episodes get done, from inside the compiled program (e.g.
    :class:`lnnmpc.train.report.StepProgress`)."""
    program = rollout_program(agent, env, episodes, steps)
    with reporting(progress, steps or env.episode_length):
        records = jax.block_until_ready(program(state, key))
    return {name: np.swapaxes(np.asarray(value), 0, 1) for name, value in records.items()}


def op_model_functions(agent, state):
    """(predict, step) of an OP agent's world model for :func:`lnnmpc.analysis.metrics.k_step_errors`:
    predict(z (S, N), a (S, A)) -> predicted next observation (mean) (S, d); step(z, a) -> next latent (S, N),
    the planner's mean transition (the prediction read by the encoder with Δt = 1, Algorithm 5)."""
    if getattr(getattr(agent.config, "model", None), "objective", None) != "op":
        raise ValueError(f"k-step observation prediction needs an OP agent, got {type(agent).__name__} with "
                         f"config {getattr(agent.config, 'model', None)}")
    params = state.params
    predict = jax.jit(lambda z, a: agent._apply(params, z, a, method="predict")[0])
    step = jax.jit(lambda z, a: agent._apply(params, z, a, method="transition"))
    return (lambda z, a: np.asarray(predict(jnp.asarray(z, jnp.float32), jnp.asarray(a, jnp.float32))),
            lambda z, a: np.asarray(step(jnp.asarray(z, jnp.float32), jnp.asarray(a, jnp.float32))))
