"""Agents by name: ``make_agent("tdmpc2", obs_dim, action_dim, ...)`` builds the agent the trainer runs.

Every agent exposes the same pure functions (jit and vmap them over seeds): ``init(key) -> AgentState``,
``update(state, batch, key) -> (state, metrics)`` and ``act(...)``; the training loop only talks to them.
"""

from __future__ import annotations

from lnnmpc.agents.mppi import MPPIConfig
from lnnmpc.agents.tdmpc2 import TDMPC2, TDMPC2Config
from lnnmpc.agents.tdmpc2_model import WorldModelConfig

AGENTS = ("tdmpc2",)

SMALL_MODEL = {"enc_dim": 32, "mlp_dim": 32, "latent_dim": 16}
SMALL_PLANNER = {"num_samples": 64, "num_policy_trajectories": 8, "num_elites": 8, "iterations": 2}


def make_agent(name: str, obs_dim: int, action_dim: int, *, model_size: int = 5, small: bool = False):
    """The agent called ``name`` for observations (obs_dim,) and actions (action_dim,).

    ``small`` shrinks networks and planner to CPU-smoke-test sizes. Raises ValueError naming the known agents.
    """
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; known: {', '.join(AGENTS)}")
    model = WorldModelConfig.from_size(obs_dim, action_dim, model_size, **(SMALL_MODEL if small else {}))
    planner = MPPIConfig(**SMALL_PLANNER) if small else MPPIConfig()
    return TDMPC2(TDMPC2Config(model=model, planner=planner))
