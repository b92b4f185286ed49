"""``lnnmpc.evaluate(run, ...)``: re-evaluate a run's checkpoint under any corruption, on MJX or on dm_control.

    import lnnmpc
    result = lnnmpc.evaluate("runs/walker-run/tdmpc2/20260101-120000-clean", obs="noise=0.3", episodes=10,
                             backend="dm_control")
    result.mean, result.std, result.path          # path: the CSV written under <run>/evals/

Each seed's policy plays ``episodes`` deterministic episodes (the training evaluation protocol: MPPI without
exploration noise, each episode with its own seed). ``backend="mjx"`` runs them in parallel in one compiled
program on the default JAX device with the physics profile the run trained on; ``backend="dm_control"`` runs the
same agent on the original dm_control simulator on the CPU (:mod:`lnnmpc.train.dm_backend`). The CSV has one
row per (seed, episode) with the checkpoint's environment step, backend and corruption options. A run folder
without its checkpoints (one brought back from a GPU) is evaluated from its ``policy.npz``
(:mod:`lnnmpc.train.policy_file`), the newest checkpoint's parameters, or at an earlier evaluation's step from
that evaluation's snapshot in ``policies/`` (runs trained with ``eval_policies``). ``actor="prior"`` lets the
policy prior act alone instead of MPPI (:mod:`lnnmpc.agents.actor`): what planning adds to the learned policy.
``planner={"iterations": 12}`` plans with other MPPI settings than the run trained with (planner-only keys,
:func:`lnnmpc.agents.overrides.planner_keys`; the parameters do not depend on them); the CSV's name and its
``planner`` column say which.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import os
import sys

import jax
import numpy as np

from lnnmpc.agents.actor import PriorActing, check_actor, with_actor
from lnnmpc.agents.overrides import apply_planner_overrides
from lnnmpc.train import runfolder
from lnnmpc.train.checkpoint import all_steps, restore_checkpoint
from lnnmpc.train.compat import check_layout, state_signature
from lnnmpc.train.config import BACKENDS, ConfigError, TrainConfig, obs_tag, parse_obs, require_int
from lnnmpc.train.loop import LoopConfig, TrainingLoop
from lnnmpc.train.policy_file import POLICY_FILE, SNAPSHOT_DIR, policy_path, policy_step, restore_policy, snapshot_steps
from lnnmpc.train.report import StepProgress
from lnnmpc.train.setup import build_loop, config_env, enable_compile_cache
from lnnmpc.train.sharding import SeedPlacement


@dataclasses.dataclass(frozen=True)
class EvalResult:
    """Returns (seeds, episodes) of one evaluation and where they were written."""

    returns: np.ndarray
    checkpoint: int
    backend: str
    obs: dict
    path: str

    @property
    def mean(self) -> float:
        return float(self.returns.mean())

    @property
    def std(self) -> float:
        """Over seeds' mean returns with several seeds, over episodes with one."""
        per_seed = self.returns.mean(axis=1)
        return float(per_seed.std() if per_seed.size > 1 else self.returns.std())


@dataclasses.dataclass(frozen=True)
class Policy:
    """A run's trained agent at one checkpoint: the run's configuration, its loop and the seed-batched state."""

    config: TrainConfig
    loop: TrainingLoop
    agent_state: object
    checkpoint: int

    def seed_state(self, index: int) -> object:
        """The agent state of trained seed ``index`` (``agent_state`` with the seed axis taken off every leaf)."""
        return jax.tree_util.tree_map(lambda x: x[index], self.agent_state)


def check_observation_size(env, policy: Policy) -> None:
    """Evaluation corruptions must keep the observation the agent was trained on (remove_vel as in training)."""
    if env.observation_size != policy.loop.env.observation_size:
        raise ConfigError(f"observation options {env.corruption} give {env.observation_size} dimensions, the "
                          f"run's agent takes {policy.loop.env.observation_size} (remove_vel must match training)")


def choose_checkpoint(run: str, checkpoint: int | None) -> int:
    """A step of ``run`` with a complete checkpoint, its ``policy.npz`` or an evaluation's policy snapshot
    (``policies/``; the newest step by default)."""
    exported = policy_step(run)
    steps = sorted({*all_steps(run), *snapshot_steps(run), *([] if exported is None else [exported])})
    if not steps:
        raise ConfigError(f"{run!r} has no complete checkpoint, no {POLICY_FILE} and no {SNAPSHOT_DIR}/")
    if checkpoint is None:
        return steps[-1]
    if checkpoint not in steps:
        raise ConfigError(f"checkpoint {checkpoint!r} is not in {run}; available: {', '.join(map(str, steps))}")
    return checkpoint


def load_policy(run: str, checkpoint: int | None = None) -> Policy:
    """Restores the agent state of all seeds from a checkpoint or ``policy.npz`` (the newest by default)."""
    config = runfolder.saved_config(run)
    step = choose_checkpoint(run, checkpoint)
    loop = build_loop(config)
    check_layout(run, state_signature(loop, config.seeds))
    return _restored(Policy(config=config, loop=loop, agent_state=None, checkpoint=step), run)


def policy_at(policy: Policy, run: str, checkpoint: int) -> Policy:
    """``policy`` (same configuration and loop: compiled programs are reused) with the agent state of
    ``checkpoint`` of ``run``."""
    return _restored(dataclasses.replace(policy, checkpoint=choose_checkpoint(run, checkpoint)), run)


def _restored(policy: Policy, run: str) -> Policy:
    """``policy`` with the agent state of its (existing) ``checkpoint`` step of ``run``: from the checkpoint, or
    where the run has none at that step (a run folder back from a GPU) from its ``policy.npz`` or that step's
    evaluation snapshot."""
    keys = jax.random.split(jax.random.key(0), policy.config.seeds)
    if policy.checkpoint not in all_steps(run):
        like = jax.jit(jax.vmap(policy.loop.agent.init))(keys)
        agent_state = restore_policy(run, like, policy_path(run, policy.checkpoint))
        return dataclasses.replace(policy, agent_state=agent_state)
    state, _ = restore_checkpoint(run, policy.checkpoint, _state_shapes(policy.config, policy.loop, keys))
    return dataclasses.replace(policy, agent_state=state.agent)


def _agent_key(agent) -> tuple:
    """What an agent computes with: its class and configuration (the prior acting: that, wrapped)."""
    if isinstance(agent, PriorActing):
        return ("prior", *_agent_key(agent.agent))
    return (type(agent).__module__, type(agent).__qualname__, agent.config)


class SameProgram:
    """An (agent, env) pair that hashes and compares by what programs over it compute: the agent's class and
    configuration, the environment's task, physics and corruptions, the default device (by identity where the
    agent's configuration cannot be hashed). A ``functools.lru_cache`` key: another agent object of the same
    configuration on an equal environment (a second evaluation of a run, a copy of its folder) finds the program
    already traced and compiled (~10-20 s on a CPU for MJX physics and MPPI)."""

    def __init__(self, agent, env):
        self.agent, self.env = agent, env
        key = (_agent_key(agent), env.spec, env.action_repeat, env.physics_options, env.corruption, jax.devices()[0])
        try:
            hash(key)
        except TypeError:
            key = (id(agent), id(env))  # the entry holds both, so their ids stay theirs while it lives
        self.key = key

    def __hash__(self) -> int:
        return hash(self.key)

    def __eq__(self, other) -> bool:
        return isinstance(other, SameProgram) and self.key == other.key


@functools.lru_cache(maxsize=8)
def _evaluation_program(pair: SameProgram, episodes: int, seeds: int):
    """``jit(vmap(evaluate))`` of a one-device loop over ``pair``'s agent and env (seeds: part of the key only)."""
    loop = TrainingLoop(pair.agent, pair.env, pair.env, LoopConfig(eval_episodes=episodes))
    return SeedPlacement(1).compile(loop.evaluate)


_SHAPES: collections.OrderedDict = collections.OrderedDict()


def _state_shapes(config: TrainConfig, loop: TrainingLoop, keys: jax.Array):
    """The training state's shapes and dtypes for ``config`` (``eval_shape`` of the seeds' ``loop.init``, which
    traces environments, agent and replay: seconds), reused for equal configurations in this process."""
    key = repr(config)  # a frozen dataclass of plain values and dicts: equal configurations, equal text
    if key not in _SHAPES:
        _SHAPES[key] = jax.eval_shape(jax.vmap(loop.init), keys)
        while len(_SHAPES) > 8:
            _SHAPES.popitem(last=False)
    _SHAPES.move_to_end(key)
    return _SHAPES[key]


def mjx_evaluator(agent, env, episodes: int, seeds: int):
    """A compiled evaluation of ``episodes`` deterministic episodes per seed on MJX ``env``, acting with
    ``agent.act`` (MPPI; the prior alone under :func:`lnnmpc.agents.actor.with_actor`): returns
    ``run(agent_state, key) -> (seeds, episodes)`` returns, the seeds' keys split from ``key``; the episodes are
    those the trainer's evaluations play with the same key (:func:`lnnmpc.train.loop.play_episodes`; their returns
    bit for bit only at the trainer's episode count: another batch width rounds differently). Call ``run``
    for as many agent states as needed; a later evaluator of an equal agent configuration, environment and sizes
    in the same process runs the same compiled program."""
    placement = SeedPlacement(1)
    program = _evaluation_program(SameProgram(agent, env), episodes, seeds)

    def run(agent_state, key: jax.Array) -> np.ndarray:
        keys = placement.put(jax.random.split(key, seeds))
        return np.asarray(program(placement.put(agent_state), keys))

    return run


def require_actor(actor: str) -> None:
    """:func:`lnnmpc.agents.actor.check_actor` as a :class:`ConfigError` (the CLI's exit 2), naming the actors."""
    try:
        check_actor(actor)
    except ValueError as error:
        raise ConfigError(str(error)) from None


def planner_tag(planner: dict | None) -> str:
    """``{"iterations": 12, "plan_horizon": 5}`` -> ``"iterations=12 plan_horizon=5"`` (sorted; "" for none)."""
    return " ".join(f"{key}={value}" for key, value in sorted((planner or {}).items()))


def with_planner(agent, planner: dict | None):
    """``agent`` rebuilt with the planner-only overrides ``planner`` (the same class and trained configuration
    otherwise, so its parameters fit); ConfigError names a key that is not a planner setting."""
    if not planner:
        return agent
    try:
        return type(agent)(apply_planner_overrides(agent.config, planner))
    except ValueError as error:
        raise ConfigError(str(error)) from None


def evaluate(run: str, *, obs: str | dict | None = None, episodes: int = 10, backend: str = "mjx",
             checkpoint: int | None = None, seed: int = 0, out: str | None = None, actor: str = "planner",
             planner: dict | None = None, verbose: bool = True) -> EvalResult:
    """Evaluates a run's checkpoint; writes a CSV (``out`` or ``<run>/evals/<backend>-<obs>-<step>.csv``).

    ``obs``: corruption options (text like "noise=0.3" or a dict; None: the run's evaluation corruptions).
    ``episodes``: per seed. ``checkpoint``: an environment step with a checkpoint (None: the latest).
    ``actor``: "planner" (MPPI, the training evaluation's) or "prior" (the policy prior alone, tanh of its mean;
    :mod:`lnnmpc.agents.actor`), whose CSV is named ``<backend>-prior-<obs>-<step>.csv``.
    ``planner``: MPPI settings to plan with instead of the run's ({key: value}, e.g. ``{"iterations": 12}``);
    the CSV is named ``<backend>-<key><value>...-<obs>-<step>.csv``.
    ``seed``: the episodes' key (``jax.random.key(seed)``; dm_control's initial states from it too): runs and
    settings evaluated with one seed play the same episodes (``lnnmpc.train.paired`` compares them episode by
    episode). The CSV's ``eval_seed`` column records it; a seed other than 0 names the CSV ``...-seed<k>-<obs>-...``.
    """
    if backend not in BACKENDS:
        raise ConfigError(f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}")
    require_int("episodes", episodes, 1)
    require_actor(actor)  # before anything loads
    config = runfolder.saved_config(run)
    options = dict(config.eval_obs) if obs is None else parse_obs(obs)
    step = choose_checkpoint(run, checkpoint)
    try:
        env = config_env(config, options)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    enable_compile_cache(config.compile_cache)
    policy = load_policy(run, step)
    check_observation_size(env, policy)
    key = jax.random.key(seed)
    agent = with_actor(with_planner(policy.loop.agent, planner), actor)
    if backend == "mjx":
        returns = mjx_evaluator(agent, env, episodes, config.seeds)(policy.agent_state, key)
    else:
        from lnnmpc.train.dm_backend import run_episodes

        unit = f"agent steps of {config.seeds} seed(s) x {episodes} episodes on dm_control"
        returns = run_episodes(env, agent, policy.agent_state, episodes, key, seed=seed,
                               progress=StepProgress(unit) if verbose else None)
    by = "" if actor == "planner" else f"{actor}-"
    by += "".join(f"{key}{value}-" for key, value in sorted((planner or {}).items()))
    by += "" if seed == 0 else f"seed{seed}-"  # other episodes than the default key's: a file of their own
    path = out or os.path.join(run, "evals", f"{backend}-{by}{obs_tag(options)}-{step}.csv")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if os.path.exists(path):
        os.remove(path)
    runfolder.append_csv(path, [
        {"env_step": step, "seed": s, "episode": e, "return": float(returns[s, e]), "backend": backend,
         "obs": obs_tag(options), "actor": actor, "planner": planner_tag(planner), "eval_seed": seed}
        for s in range(returns.shape[0]) for e in range(returns.shape[1])])
    result = EvalResult(returns=returns, checkpoint=step, backend=backend, obs=options, path=path)
    if verbose:
        acting = "" if actor == "planner" else f", acting with the {actor}"
        acting += f", planning with {planner_tag(planner)}" if planner else ""
        sys.stdout.write(f"{config.task} {config.agent} checkpoint {step:,} on {backend} with "
                         f"{obs_tag(options)}{acting}: return {result.mean:.1f} ± {result.std:.1f} "
                         f"({returns.shape[0]} seed(s) x {episodes} episodes) -> {path}\n")
    return result
