"""The on-device training loop: chunks of agent steps (act -> env step -> replay insert -> update) in one scan.

All state of one seed is a :class:`TrainState` pytree; the host ``vmap``s every function over seeds and only
touches the state between chunks. The schedule (SPEC §1) is driven by the host with three compiled programs:
:func:`seed_chunk` (uniform random actions, no updates), :func:`update_burst` (as many updates as agent steps of
the seed phase) and :func:`train_chunk` (MPPI with exploration noise, ``num_envs`` updates per iteration so that
there is one update per agent step).

The loop is agent-agnostic: it talks to the agent only through the protocol documented in
:mod:`lnnmpc.agents.registry` (``init``, ``update``, ``sequence_length``, ``sequence_lead``, ``initial_carry``,
``act``, ``observe``, ``replay_record``). Each environment has an agent-defined *acting carry* (TD-MPC2: the
planner's warm start; LNN agents: also the encoder state and the previous action); the loop resets it to
``agent.initial_carry()`` at every episode start, before acting.

Replay records come from ``agent.replay_record(obs_t, a_t, r_t, dt_t, carry_t)`` with ``carry_t`` the carry the
agent acted from at step t (after the reset): obs_t, the action a_t and the reward r_t it earned, plus whatever
the agent stores; the final observation of an episode is its own record (action 0, reward 0), written on the
iteration that resets the environment (an iteration that takes no environment step; episodes have a fixed
length, so all environments of a seed reset together). Updates sample windows of ``agent.sequence_length``
records that never cross an episode after their first ``agent.sequence_lead`` records (0 but for an LNN agent's
burn-in with ``learn_episode_starts``); the batch carries the records' episode-start flags as ``"first"``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from lnnmpc import envs as envs_lib
from lnnmpc.agents.actor import with_actor
from lnnmpc.agents.exploration import colored_noise
from lnnmpc.agents.registry import acting_latent
from lnnmpc.replay import ReplayState, replay_add, replay_init, replay_sample


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Static settings of the loop (the trainer's CLI builds it).

    ``guard_empty_replay``: an update drawn from a buffer that holds no valid window yet keeps the agent as it was
    (a select between the old and the new agent state after every update: one more pass over all parameters and
    optimiser states, 0.72 of the 5.81 ms of cartpole's 8-seed TD-MPC2 update on an H200, benchmark run 27). The
    trainer turns it off when its seed phase provably leaves a window in every stream
    (:func:`windows_after_seed_phase`), which makes the select a no-op.

    ``eval_prior``: :meth:`TrainingLoop.evaluate_logged` also plays the evaluation's episodes with the policy
    prior acting alone (the agent's ``act_prior``; :func:`lnnmpc.agents.actor.with_actor`).

    ``explore_noise_beta``: None: the agent's own exploration noise (white). β >= 0: every environment draws one
    colored sequence (episode_length, A) with spectrum 1/f^β at each episode start
    (:func:`lnnmpc.agents.exploration.colored_noise`; :class:`ExploringTrainState`), and :meth:`train_chunk`
    passes its step-t sample to the agent's ``act`` as ``explore_noise``.

    ``seed_noise_beta``: None: :meth:`seed_chunk` acts uniformly at random. β >= 0: it acts with such colored
    sequences (unit std, drawn at each episode start, clipped to [-1, 1]); an episode running when the seed phase
    ends keeps its sequence (as its exploration noise, with ``explore_noise_beta``).

    ``updates_per_step``: updates per agent step (the update-to-data ratio; 1 = TD-MPC2's): :meth:`train_chunk`
    makes ``num_envs * updates_per_step`` updates per iteration, and the trainer's burst after the seed phase
    ``updates_per_step`` per seed-phase agent step.
    """

    num_envs: int = 1
    batch_size: int = 256
    replay_capacity: int = 100_300
    eval_episodes: int = 10
    guard_empty_replay: bool = True
    eval_prior: bool = False
    explore_noise_beta: float | None = None
    seed_noise_beta: float | None = None
    updates_per_step: int = 1

    def __post_init__(self):
        for name in ("num_envs", "batch_size", "replay_capacity", "eval_episodes", "updates_per_step"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        for name in ("guard_empty_replay", "eval_prior"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        for name in ("explore_noise_beta", "seed_noise_beta"):
            if getattr(self, name) is not None and not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0 or None, got {getattr(self, name)!r}")

    @property
    def updates_per_iteration(self) -> int:
        """Updates per loop iteration: ``updates_per_step`` for each of the ``num_envs`` agent steps."""
        return self.num_envs * self.updates_per_step


def windows_after_seed_phase(seed_iterations: int, episode_length: int, sequence_length: int,
                             capacity: int) -> bool:
    """Whether every stream's buffer of ``capacity`` slots holds a valid window of ``sequence_length`` records
    from the end of ``seed_iterations`` loop iterations (one record per stream each) on, whatever the agent's
    ``sequence_lead``.

    Each iteration writes one record per stream and an episode is ``episode_length`` decisions plus its final
    observation, so once ``sequence_length`` records are written the first episode's first ones form a window,
    if an episode holds that many. Once the ring overwrites, its newest ``capacity`` records end with an
    episode's first k records: k >= ``sequence_length`` is a window, else the ``capacity - k >= sequence_length``
    records before them (``capacity >= 2 sequence_length - 1``) hold one of the previous episode. Sufficient,
    not necessary (a burn-in lead lets windows reach into the episode before); other configurations keep the
    guard.
    """
    return (seed_iterations >= sequence_length and episode_length + 1 >= sequence_length
            and capacity >= 2 * sequence_length - 1)


@struct.dataclass
class TrainState:
    """One seed's training state: agent, replay buffer, environments (num_envs,), acting carries, RNG."""

    agent: Any
    replay: ReplayState
    env: Any
    carry: Any  # the agent's acting carry, leaves (num_envs, ...)
    episode_return: jax.Array  # (num_envs,) return so far in the current episode
    key: jax.Array


@struct.dataclass
class ExploringTrainState(TrainState):
    """:class:`TrainState` of a loop with colored noise (``LoopConfig.explore_noise_beta`` or
    ``seed_noise_beta``): plus the current episodes' noise (num_envs, episode_length, A). A class of its own so
    that the state of every other run keeps its layout (and its checkpoints their signature,
    :func:`lnnmpc.train.compat.layout_signature`)."""

    explore_noise: jax.Array = None


class TrainingLoop:
    """Compiled pieces of training for one agent on one environment (vmap them over seeds).

    Raises ValueError for ``config.eval_prior`` with an agent that has no policy prior (no ``act_prior``)."""

    def __init__(self, agent: Any, env: envs_lib.Env, eval_env: envs_lib.Env, config: LoopConfig):
        self.agent, self.env, self.eval_env, self.config = agent, env, eval_env, config
        self.prior = with_actor(agent, "prior") if config.eval_prior else None  # acts in evaluate_logged

    def initial_carries(self, n: int) -> Any:
        """The agent's initial acting carry stacked for ``n`` environments."""
        return stacked_initial_carry(self.agent, n)

    def _reset_carries(self, carry: Any, first: jax.Array) -> Any:
        """Carries of environments at their first step (``first`` (n,)) back to the initial carry."""
        return _where(first, self.initial_carries(first.shape[0]), carry)

    # ------------------------------------------------------------------------------------------ init
    def init(self, key: jax.Array) -> TrainState:
        """One seed's state before training: the agent's parameters and optimiser, an empty replay buffer sized by
        ``replay_capacity`` for ``num_envs`` environments, the environments reset, the initial acting carries, zero
        episode returns and, with coloured exploration noise, each environment's first episode of noise."""
        k_agent, k_env, k_loop = jax.random.split(key, 3)
        m, act_dim = self.config.num_envs, self.env.action_size
        record = self.agent.replay_record(jnp.zeros((self.env.observation_size,)), jnp.zeros((act_dim,)),
                                          jnp.zeros(()), jnp.ones(()), self.agent.initial_carry())
        fields = dict(agent=self.agent.init(k_agent), replay=replay_init(record, self.config.replay_capacity, m),
                      env=jax.vmap(self.env.reset)(jax.random.split(k_env, m)), carry=self.initial_carries(m),
                      episode_return=jnp.zeros((m,)), key=k_loop)
        c = self.config
        if c.explore_noise_beta is None and c.seed_noise_beta is None:
            return TrainState(**fields)
        beta = c.seed_noise_beta if c.seed_noise_beta is not None else c.explore_noise_beta
        return ExploringTrainState(**fields, explore_noise=self._episode_noise(jax.random.fold_in(k_loop, 1), beta))

    def _episode_noise(self, key: jax.Array, beta: float) -> jax.Array:
        """(num_envs, episode_length, A) fresh colored noise of spectrum 1/f^``beta``, one sequence per
        environment."""
        noise = colored_noise(key, beta, self.env.episode_length, (self.config.num_envs, self.env.action_size))
        return jnp.moveaxis(noise, 0, 1)

    def _colored_sample(self, ts: TrainState, first: jax.Array, key: jax.Array,
                        beta: float | None) -> tuple[TrainState, Any]:
        """With colored noise of spectrum 1/f^``beta``: the state with fresh sequences for the environments at their
        first step (``first`` (num_envs,)) and each environment's sample for its step t, (num_envs, A); with
        ``beta`` None: (ts, None)."""
        if beta is None:
            return ts, None
        noise = jnp.where(first[:, None, None], self._episode_noise(key, beta), ts.explore_noise)
        t = jnp.minimum(ts.env.t, self.env.episode_length - 1)
        return ts.replace(explore_noise=noise), noise[jnp.arange(noise.shape[0]), t]

    def _exploration(self, ts: TrainState, first: jax.Array, key: jax.Array) -> tuple[TrainState, Any]:
        """The training chunk's exploration noise: :meth:`_colored_sample` with ``explore_noise_beta`` (None: the
        agent's own white noise)."""
        return self._colored_sample(ts, first, key, self.config.explore_noise_beta)

    # ------------------------------------------------------------------------------------------ steps
    def _env_step(self, ts: TrainState, action: jax.Array, carry: Any, next_carry: Any, key: jax.Array):
        """Records the transition, steps (or resets after the last step of an episode) every environment.

        ``carry``: the carries the agent acted from (stored in the record); ``next_carry``: the ones it returned.
        """
        env = ts.env
        terminal = env.done  # (m,)
        action = jnp.where(terminal[:, None], 0.0, action)
        # one physics program steps the running environments and resets the finished ones (Env.step_or_reset)
        new_env = jax.vmap(self.env.step_or_reset)(env, action, terminal,
                                                   jax.random.split(key, self.config.num_envs))
        reward = jnp.where(terminal, 0.0, new_env.reward)
        record = jax.vmap(self.agent.replay_record)(env.obs, action, reward, env.dt, carry)
        replay = replay_add(ts.replay, record, env.t == 0)
        finished = jnp.where(terminal, ts.episode_return, jnp.nan)  # returns of episodes that just ended
        episode_return = jnp.where(terminal, 0.0, ts.episode_return + reward)
        return ts.replace(replay=replay, env=new_env, carry=next_carry, episode_return=episode_return), {
            "reward": reward, "episode_return": finished}

    def _update(self, ts: TrainState, key: jax.Array):
        k_sample, k_update = jax.random.split(key)
        with jax.named_scope("replay_sample"):
            records, first, valid = replay_sample(ts.replay, k_sample, self.config.batch_size,
                                                  self.agent.sequence_length, self.agent.sequence_lead)
        agent, metrics = self.agent.update(ts.agent, {**records, "first": first}, k_update)
        if self.config.guard_empty_replay:  # keep the old agent if the buffer had no valid window yet
            with jax.named_scope("keep_if_valid"):
                agent = jax.tree_util.tree_map(lambda new, old: jnp.where(valid.all(), new, old), agent, ts.agent)
        return ts.replace(agent=agent), metrics

    def seed_chunk(self, ts: TrainState, length: int) -> tuple[TrainState, dict]:
        """``length`` iterations of random actions, uniform or colored (``seed_noise_beta``; no updates; the agent
        still observes them)."""
        def body(ts, _):
            key, k_act, k_env = jax.random.split(ts.key, 3)
            first = ts.env.t == 0
            ts, colored = self._colored_sample(ts, first, jax.random.fold_in(k_act, 1), self.config.seed_noise_beta)
            action = (jax.random.uniform(k_act, (self.config.num_envs, self.env.action_size), minval=-1, maxval=1)
                      if colored is None else jnp.clip(colored, -1.0, 1.0))
            carry = self._reset_carries(ts.carry, first)
            observe = jax.vmap(lambda c, o, dt, a, f: self.agent.observe(ts.agent, c, o, dt, a, first_step=f))
            next_carry = observe(carry, ts.env.obs, ts.env.dt, action, first)
            return self._env_step(ts.replace(key=key), action, carry, next_carry, k_env)

        return jax.lax.scan(body, ts, None, length=length)

    def update_burst(self, ts: TrainState, num_updates: int) -> tuple[TrainState, dict]:
        """``num_updates`` updates in a row (after the seed phase)."""
        def body(ts, _):
            key, k_update = jax.random.split(ts.key)
            return self._update(ts.replace(key=key), k_update)

        return jax.lax.scan(body, ts, None, length=num_updates)

    def train_chunk(self, ts: TrainState, length: int) -> tuple[TrainState, dict]:
        """``length`` iterations of planning with exploration, an environment step and ``num_envs *
        updates_per_step`` updates."""
        m, num_updates = self.config.num_envs, self.config.updates_per_iteration

        def body(ts, _):
            key, k_act, k_env, k_update = jax.random.split(ts.key, 4)
            first = ts.env.t == 0
            carry = self._reset_carries(ts.carry, first)
            ts, noise = self._exploration(ts, first, jax.random.fold_in(k_act, 1))  # None: the agent's white noise
            act = jax.vmap(lambda c, o, dt, k, f, n: self.agent.act(ts.agent, c, o, dt, k, explore=True,
                                                                    first_step=f, explore_noise=n))
            action, next_carry = act(carry, ts.env.obs, ts.env.dt, jax.random.split(k_act, m), first, noise)
            ts, out = self._env_step(ts.replace(key=key), action, carry, next_carry, k_env)
            ts, metrics = jax.lax.scan(lambda ts, k: self._update(ts, k), ts,
                                       jax.random.split(k_update, num_updates))
            return ts, {**out, **jax.tree_util.tree_map(lambda x: x[-1], metrics)}

        return jax.lax.scan(body, ts, None, length=length)

    # -------------------------------------------------------------------------------------- evaluate
    def evaluate(self, agent: Any, key: jax.Array) -> jax.Array:
        """Returns (eval_episodes,) of deterministic MPPI episodes, run in parallel, each with its own seed
        (episode i's from ``fold_in(key, i)``: more episodes with the same key extend the set of initial states;
        another batch width is another program, whose round-off can move a chaotic episode's return)."""
        return self._eval_episodes(agent, key, latents=False)[0]

    def evaluate_with_rank(self, agent: Any, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """:meth:`evaluate`'s returns (eval_episodes,) and each episode's effective rank (eval_episodes,) of its
        latent matrix Z (T, N) (:func:`effective_rank`; the thesis's Figs. 5.11–5.12 over training)."""
        total, z = self._eval_episodes(agent, key, latents=True)  # z: (T, n, N)
        return total, effective_rank(jnp.swapaxes(z, 0, 1))

    def evaluate_logged(self, agent: Any, key: jax.Array) -> dict[str, jax.Array]:
        """What the trainer logs of one evaluation, by eval.csv column, each (eval_episodes,): ``return`` and
        ``effective_rank`` (:meth:`evaluate_with_rank`), and with ``config.eval_prior`` ``prior_return``: the same
        episodes (the same reset and step keys, so the same initial states) with the policy prior acting alone.

        The prior's episodes are a scan of their own after MPPI's: the planner's computation is that of a loop
        without ``eval_prior`` (its returns do not move by round-off, which a chaotic episode would amplify, as
        they did when both shared one scan and one batched physics step), and the prior's is ``evaluate`` of a loop
        whose agent is ``with_actor(agent, "prior")``."""
        total, rank = self.evaluate_with_rank(agent, key)
        columns = {"return": total, "effective_rank": rank}
        if self.prior is not None:
            columns["prior_return"] = self._eval_episodes(agent, key, latents=False, actor=self.prior)[0]
        return columns

    def _eval_episodes(self, agent: Any, key: jax.Array, latents: bool,
                       actor: Any = None) -> tuple[jax.Array, jax.Array | None]:
        """Returns (eval_episodes,) and, with ``latents``, the latents (T, eval_episodes, N) of deterministic
        episodes of the agent state ``agent`` acted by ``actor`` (default the agent itself: MPPI)."""
        record = (lambda s, carry, action, nxt: acting_latent(self.agent, agent, carry, s.obs)) if latents else None
        return play_episodes(self.agent if actor is None else actor, agent, self.eval_env, key,
                             self.config.eval_episodes, record=record)


def play_episodes(acting: Any, agent_state: Any, env: envs_lib.Env, key: jax.Array, episodes: int,
                  steps: int | None = None, record: Any = None, on_step: Any = None) -> tuple[jax.Array, Any]:
    """``episodes`` deterministic episodes (no exploration noise) of ``acting`` (an agent, or one under
    :func:`lnnmpc.agents.actor.with_actor`) with state ``agent_state``, in parallel, for ``steps`` agent steps
    (default the whole episode); episode i's reset and acting keys from ``fold_in(key, i)``
    (:func:`evaluation_keys`), as every evaluation of the trainer plays them.

    Returns each episode's return (episodes,) and what ``record(state, carry, action, next_state)`` gives at each
    step, stacked time-major (T, episodes, ...) (None without ``record``): ``state`` the environments' states
    (episodes,) before the step, ``carry`` the acting carries after acting on ``state.obs``. ``on_step(t)``, where
    given, is called on the host with each agent step t done (``jax.debug.callback``, unordered: a progress line;
    XLA's persistent cache keeps no program that holds a host callback, so each process compiles such a program)."""
    k_reset, k_act = evaluation_keys(key, episodes)
    env_state = jax.vmap(env.reset)(k_reset)
    carries = stacked_initial_carry(acting, episodes)

    def body(loop_carry, t):
        s, carry, total = loop_carry
        act = jax.vmap(lambda c, o, dt, kk, f: acting.act(agent_state, c, o, dt, kk, explore=False, first_step=f))
        action, carry = act(carry, s.obs, s.dt, evaluation_step_keys(k_act, t), s.t == 0)
        nxt = jax.vmap(env.step)(s, action)
        if on_step is not None:
            jax.debug.callback(on_step, t)
        return (nxt, carry, total + nxt.reward), (None if record is None else record(s, carry, action, nxt))

    (_, _, total), records = jax.lax.scan(body, (env_state, carries, jnp.zeros((episodes,))),
                                          jnp.arange(steps or env.episode_length))
    return total, records


def stacked_initial_carry(agent: Any, *shape: int) -> Any:
    """``agent.initial_carry()`` broadcast to leading axes ``shape`` (e.g. (environments,) or (seeds, episodes))."""
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (*shape, *jnp.shape(x))), agent.initial_carry())


def evaluation_keys(key: jax.Array, episodes: int) -> tuple[jax.Array, jax.Array]:
    """(reset keys (episodes,), acting keys (episodes,)) of an evaluation: episode i's from ``fold_in(key, i)``
    alone, so the first k episodes of an evaluation of n are those of an evaluation of k with the same key."""
    pairs = jax.vmap(lambda i: jax.random.split(jax.random.fold_in(key, i)))(jnp.arange(episodes))  # (n, 2)
    return pairs[:, 0], pairs[:, 1]


def evaluation_step_keys(act_keys: jax.Array, t: jax.Array) -> jax.Array:
    """The planner's keys (episodes,) at agent step ``t`` of the episodes of ``act_keys`` (episodes,)."""
    return jax.vmap(jax.random.fold_in, in_axes=(0, None))(act_keys, t)


def effective_rank(z: jax.Array) -> jax.Array:
    """Effective rank (Roy & Vetterli 2007) of matrices z (..., T, N) -> (...): exp of the entropy of the
    normalised singular values, as :func:`lnnmpc.analysis.metrics.effective_rank` (float64 NumPy) computes it,
    here in the program's precision on the device."""
    sigma = jnp.linalg.svd(z, compute_uv=False)
    p = sigma / jnp.maximum(sigma.sum(axis=-1, keepdims=True), jnp.finfo(sigma.dtype).tiny)
    return jnp.exp(-jnp.sum(jnp.where(p > 0, p * jnp.log(jnp.where(p > 0, p, 1.0)), 0.0), axis=-1))


def _where(mask: jax.Array, on_true: Any, on_false: Any) -> Any:
    """Pick leaves of ``on_true`` where ``mask`` (n,) is set, else ``on_false`` (leaves with leading axis n)."""
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (jnp.ndim(a) - 1)), a, b), on_true, on_false)
