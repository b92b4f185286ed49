"""Agents by name: ``make_agent("cfc-zp-det", obs_dim, action_dim, ...)`` builds the agent the trainer runs.

Agent protocol (what :class:`lnnmpc.train.loop.TrainingLoop` and the evaluation tools rely on). All methods are
pure; the loop ``jit``s them, ``vmap``s them over seeds and the per-environment ones over environments:

* ``init(key) -> AgentState``: parameters, optimiser states, ... (any pytree).
* ``update(state, batch, key) -> (state, metrics)``: one update on ``batch``, the agent's replay records as
  time-major windows (leaves ``(sequence_length, B, ...)``) that never cross an episode after their first
  ``sequence_lead`` records, plus ``batch["first"]`` ``(sequence_length, B)`` bool: the records that start one.
* ``sequence_length``: records per training window (``tdmpc2``: H + 1; LNN agents: burn-in T + H + 1).
* ``sequence_lead``: records at a window's start that may precede its episode (0; LNN agents with
  ``learn_episode_starts``: the burn-in T).
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

Names: ``tdmpc2`` (:mod:`lnnmpc.agents.tdmpc2`) and the eight LNN-TD-MPC2 variants ``{cfc,ltc}-{zp,op}-{det,
stoch}`` (:mod:`lnnmpc.agents.lnn`). ``overrides`` sets hyperparameters by field name
(:mod:`lnnmpc.agents.overrides`; e.g. ``{"burn_in": 20, "lambda_": 0.9, "plan_horizon": 5}``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from lnnmpc.agents.mppi import MPPIConfig
from lnnmpc.agents.overrides import apply_overrides
from lnnmpc.agents.tdmpc2 import TDMPC2, TDMPC2Config
from lnnmpc.agents.tdmpc2_model import WorldModelConfig

LNN_AGENTS = tuple(f"{cell}-{objective}-{kind}" for cell in ("cfc", "ltc") for objective in ("zp", "op")
                   for kind in ("det", "stoch"))
AGENTS = ("tdmpc2", *LNN_AGENTS)

SMALL_MODEL = {"enc_dim": 32, "mlp_dim": 32, "latent_dim": 16}
SMALL_PLANNER = {"num_samples": 64, "num_policy_trajectories": 8, "num_elites": 8, "iterations": 2}
# LNN agents at CPU-smoke-test size: small cell and heads, planning horizon 3, training window 4 + 8 + 1.
SMALL_LNN = {"hidden_size": 16, "mlp_dim": 32, "backbone_units": 32}
SMALL_LNN_TRAINING = {"horizon": 8, "burn_in": 4}
# Hyperparameters a new run of an LNN agent gets on a task's domain unless the user sets them (the trainer
# writes them into the run's recorded overrides, so resuming and evaluating old runs is unaffected). Walker's
# joint velocities reach ±50 and saturate the CfC's input layer: with symlog inputs cfc-zp-det scored
# 318 ± 51 at 76,848 steps (3 seeds, H100) where the raw inputs gave 42 ± 4 at 52,896
# (experiments/results/cfc-zp-det-walker-run-symlog-h100-3seeds-partial). One-step TD targets and the model
# losses on the planner's own 1-2 step rollouts (not the thesis's TD(0.95) and encoder latents only) took
# cfc-zp-det from 89.6 (earlier 232.5) to 540.2 at 64,896 steps (2 seeds, H100; TD-MPC2 687.7):
# experiments/results/cfc-walker-ablations-h100-60k. Starting the deeper rollouts from every third window
# position only (rollout_stride=3) cuts the 4-seed walker update from 16.26 to 11.83 ms (H100) and learned as
# well: 690.3 at 228,576 steps against 671.6 at 204,640 (3 seeds;
# experiments/results/cfc-zp-det-walker-run-stride3-h100-3seeds-200k). Windows of 16 learning steps, planning
# over 3, learning the episodes' first steps and, for the agents that can carry it (*-zp-det), a 256-wide SimNorm
# latent head: 755.1 at 200,192 steps over 4 seeds (one per H200; the defaults before them: 690.3 at 228,576, 3
# seeds), 638.2 under observation noise 0.1 (2 seeds; the defaults before them: 558.8):
# experiments/results/cfc-walker-simnorm-latent256-starts-200k-h200 and
# experiments/results/cfc-walker-noise0.1-simnorm-latent256-starts-200k-h200. Measured on walker with cfc-zp-det
# only, so other domains keep the thesis's.
LNN_TASK_DEFAULTS = {"walker": {"input_transform": "symlog", "lambda_": 0.0, "rollout_steps": 3,
                                "rollout_stride": 3, "horizon": 16, "plan_horizon": 3,
                                "learn_episode_starts": True}}
# Task defaults of the self-predictive deterministic LNN agents (*-zp-det) on top of LNN_TASK_DEFAULTS: the
# SimNorm latent head needs such an agent (lnn_model.LNNModelConfig).
ZP_DET_TASK_DEFAULTS = {"walker": {"latent_head": "simnorm", "latent_size": 256}}


def task_default_overrides(name: str, task: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """``overrides`` completed with the defaults of :data:`LNN_TASK_DEFAULTS` (and, for a ``*-zp-det`` agent,
    :data:`ZP_DET_TASK_DEFAULTS`) for agent ``name`` on ``task`` (``"walker-run"``: domain ``walker``); what
    ``overrides`` sets wins, and a ``latent_head`` it sets takes the head's defaults (``latent_size``) with it.
    Unchanged for ``tdmpc2``."""
    overrides = dict(overrides or {})
    if name not in LNN_AGENTS:
        return overrides
    domain = task.split("-")[0]
    defaults = dict(LNN_TASK_DEFAULTS.get(domain, {}))
    if name.endswith("-zp-det") and "latent_head" not in overrides:
        defaults.update(ZP_DET_TASK_DEFAULTS.get(domain, {}))
    return {**defaults, **overrides}


def acting_latent(agent, state, carry, obs):
    """The latent the agent plans from after reading ``obs``, (..., N): an LNN agent's latent of its encoder state
    h_t (its acting carry's ``h``, after :meth:`act` read ``obs``; h itself unless ``latent_head="simnorm"``), else
    (``tdmpc2``) its per-observation encoder applied to ``obs``."""
    if hasattr(carry, "h"):
        return agent.latent_of(state.params, carry.h, obs)
    return agent._apply(state.params, obs, method="encode")


def make_agent(name: str, obs_dim: int, action_dim: int, *, model_size: int = 5, small: bool = False,
               overrides: dict[str, Any] | None = None):
    """The agent called ``name`` for observations (obs_dim,) and actions (action_dim,).

    ``model_size`` (1 or 5, TD-MPC2's sizes) applies to ``tdmpc2``; LNN agents use the thesis's light
    configuration (:class:`lnnmpc.agents.lnn.LNNConfig`). ``small`` shrinks networks, planner (and, for LNN
    agents, the training window) to CPU-smoke-test sizes.
    ``overrides`` (applied last) maps hyperparameter names to values (numbers or strings). Raises ValueError
    naming an unknown agent or key.
    """
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; known: {', '.join(AGENTS)}")
    planner = MPPIConfig(**SMALL_PLANNER) if small else MPPIConfig()
    if name in LNN_AGENTS:
        from lnnmpc.agents.lnn import LNNTDMPC2, lnn_config

        planner = dataclasses.replace(planner, horizon=3 if small else 10)
        config = lnn_config(name, obs_dim, action_dim, planner, **(SMALL_LNN if small else {}))
        config = dataclasses.replace(config, **(SMALL_LNN_TRAINING if small else {}))
        return LNNTDMPC2(apply_overrides(config, overrides))
    model = WorldModelConfig.from_size(obs_dim, action_dim, model_size, **(SMALL_MODEL if small else {}))
    return TDMPC2(apply_overrides(TDMPC2Config(model=model, planner=planner), overrides))
