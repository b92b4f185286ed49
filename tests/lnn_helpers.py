"""Shared pieces of the LNN-TD-MPC2 tests: tiny agents and a fast-compiling jit (CPU CI time is compile time)."""

from __future__ import annotations

import jax

from lnnmpc.agents.registry import make_agent

# Tiny LNN-TD-MPC2: 8 neurons, 16-wide heads, 11 value bins, window burn-in 3 + horizon 4 + 1 records.
TINY = {"hidden_size": 8, "mlp_dim": 16, "backbone_units": 16, "horizon": 4, "burn_in": 3, "num_bins": 11,
        "q_dropout": 0.0, "ode_unfolds": 2}


def tiny_agent(name: str, obs_dim: int, action_dim: int, **overrides):
    return make_agent(name, obs_dim, action_dim, small=True, overrides={**TINY, **overrides})


def quick_jit(fn, **kwargs):
    """``jax.jit`` with XLA's CPU backend optimisations off: half the compile time, which dominates these tests."""
    return jax.jit(fn, compiler_options={"xla_backend_optimization_level": 0}, **kwargs)
