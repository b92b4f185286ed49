"""Agents by name: ``make_agent("cfc-zp-det", obs_dim, action_dim, ...)`` builds the agent the trainer runs.

Agent protocol (what :class:`lnnmpc.train.loop.TrainingLoop` and the evaluation tools rely on). All methods are
pure; the loop ``jit``s them, ``vmap``s them over seeds and the per-environment ones over environments:

* ``init(key) -> AgentState``: parameters, optimiser states, ... (any pytree).
* ``update(state, batch, key) -> (state, metrics)``: one update on ``batch``, the agent's replay records as
  time-major windows (leaves ``(sequence_length, B, ...)``) that never cross an episode.
* ``sequence_length``: records per training window (``tdmpc2``: H + 1; LNN agents: burn-in T + H + 1).
* ``initial_carry() -> carry``: the per-environment *acting carry* at an episode start (any pytree, no batch
  axis): ``tdmpc2`` the planner's warm-start mean; LNN agents also the encoder state h_{t-1} and a_{t-1}.
* ``act(state, carry, obs, dt, key, *, explore, first_step) -> (action, carry)``: the action (A,) in [-1, 1]
  for one environment's observation (d,) delivered after ``dt`` () agent steps, and the carry for its next
  step. ``first_step`` (() bool, may be traced) starts an episode: the agent then ignores ``carry`` and starts
  from ``initial_carry()``; ``explore`` (static) adds exploration noise. Call it once per decision, in order.
* ``observe(state, carry, obs, dt, action, *, first_step) -> carry``: the carry after an action chosen by
  someone else (the seed phase's uniform random actions), so that a history encoder still sees every step.
* ``replay_record(obs, action, reward, dt, carry) -> record``: the pytree replay stores for one step, given
  the carry the agent acted from (after the episode-start reset).

Names: ``tdmpc2`` (:mod:`lnnmpc.agents.tdmpc2`). ``overrides`` sets hyperparameters by field name
(:mod:`lnnmpc.agents.overrides`; e.g. ``{"burn_in": 20, "lambda_": 0.9, "plan_horizon": 5}``).
"""

from __future__ import annotations

from typing import Any

from lnnmpc.agents.mppi import MPPIConfig
from lnnmpc.agents.overrides import apply_overrides
from lnnmpc.agents.tdmpc2 import TDMPC2, TDMPC2Config
from lnnmpc.agents.tdmpc2_model import WorldModelConfig

AGENTS = ("tdmpc2",)

SMALL_MODEL = {"enc_dim": 32, "mlp_dim": 32, "latent_dim": 16}
SMALL_PLANNER = {"num_samples": 64, "num_policy_trajectories": 8, "num_elites": 8, "iterations": 2}


def make_agent(name: str, obs_dim: int, action_dim: int, *, model_size: int = 5, small: bool = False,
               overrides: dict[str, Any] | None = None):
    """The agent called ``name`` for observations (obs_dim,) and actions (action_dim,).

    ``model_size`` (1 or 5, TD-MPC2's sizes). ``small`` shrinks networks and planner to CPU-smoke-test sizes.
    ``overrides`` (applied last) maps hyperparameter names to values (numbers or strings). Raises ValueError
    naming an unknown agent or key.
    """
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; known: {', '.join(AGENTS)}")
    planner = MPPIConfig(**SMALL_PLANNER) if small else MPPIConfig()
    model = WorldModelConfig.from_size(obs_dim, action_dim, model_size, **(SMALL_MODEL if small else {}))
    return TDMPC2(apply_overrides(TDMPC2Config(model=model, planner=planner), overrides))
