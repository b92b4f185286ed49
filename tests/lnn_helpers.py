"""Shared pieces of the LNN-TD-MPC2 tests: tiny agents, random training windows, a fast-compiling jit (CPU CI
time is compile time) and a physics-free linear environment."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from lnnmpc.agents.registry import make_agent

# Tiny LNN-TD-MPC2: 8 neurons, 16-wide heads, 11 value bins, window burn-in 3 + horizon 4 + 1 records.
TINY = {"hidden_size": 8, "mlp_dim": 16, "backbone_units": 16, "horizon": 4, "burn_in": 3, "num_bins": 11,
        "q_dropout": 0.0, "ode_unfolds": 2}


def tiny_agent(name: str, obs_dim: int, action_dim: int, **overrides):
    return make_agent(name, obs_dim, action_dim, small=True, overrides={**TINY, **overrides})


def quick_jit(fn, **kwargs):
    """``jax.jit`` with XLA's CPU backend optimisations off: half the compile time, which dominates these tests."""
    return jax.jit(fn, compiler_options={"xla_backend_optimization_level": 0}, **kwargs)


def perturbed_state(agent, key):
    """``agent.init(key)`` with every parameter moved off its initial value (zero-initialised heads would make every
    action 0, and comparisons of actions empty)."""
    state = agent.init(key)
    leaves, tree = jax.tree_util.tree_flatten(state.params)
    keys = jax.random.split(jax.random.fold_in(key, 1), len(leaves))
    moved = [p + 0.3 * jax.random.normal(k, p.shape, p.dtype) for p, k in zip(leaves, keys, strict=True)]
    return state.replace(params=jax.tree_util.tree_unflatten(tree, moved))


# The agent tests' shapes: observations of 5, actions of 2, batches of 8 windows.
OBS, ACT, B = 5, 2, 8


def tiny(name: str, **overrides):
    """A tiny agent ``name`` for observations of OBS and actions of ACT (TINY, then ``overrides``)."""
    return tiny_agent(name, OBS, ACT, **overrides)


def window(agent, seed: int = 0) -> dict:
    """A random time-major training window of ``agent.sequence_length`` records."""
    S, N = agent.sequence_length, agent.config.model.hidden_size
    k = jax.random.split(jax.random.key(seed), 6)
    action = jnp.tanh(jax.random.normal(k[1], (S, B, ACT)))
    return {"obs": jax.random.normal(k[0], (S, B, OBS)), "action": action,
            "reward": jax.random.uniform(k[2], (S, B)), "dt": jax.random.randint(k[3], (S, B), 1, 3) * 1.0,
            "h_prev": 0.5 * jnp.tanh(jax.random.normal(k[4], (S, B, N))),
            "prev_action": jnp.concatenate([jnp.zeros((1, B, ACT)), action[:-1]])}


@struct.dataclass
class _LinearState:
    obs: jax.Array
    dt: jax.Array
    t: jax.Array
    reward: jax.Array


class LinearEnv:
    """A pure-JAX stand-in for an Env (no MuJoCo to compile): x' = 0.9 x + action in every coordinate, reward
    -|x|^2, 4 agent steps; the interface play_episodes uses (reset, step, episode_length) and the attributes that
    name an Env's programs (lnnmpc.train.evaluate.SameProgram)."""

    episode_length, spec, action_repeat, physics_options, corruption = 4, "linear", 1, (), ()
    observation_size, action_size = 5, 2

    def reset(self, key):
        return _LinearState(obs=jax.random.normal(key, (self.observation_size,)), dt=jnp.ones(()),
                            t=jnp.zeros((), jnp.int32), reward=jnp.zeros(()))

    def step(self, state, action):
        obs = 0.9 * state.obs + jnp.pad(action, (0, self.observation_size - self.action_size))
        return state.replace(obs=obs, t=state.t + 1, reward=-jnp.sum(obs ** 2))
