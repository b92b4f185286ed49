"""On-device replay buffer of parallel environment streams, sampling windows that never cross an episode.

One buffer holds ``num_envs`` environment streams that step together, each a ring of ``capacity`` time slots.
Several seeds are several buffers: the caller ``jax.vmap``s these pure functions over a leading seed axis.

Record semantics (shapes per record, the buffer adds ``(capacity, num_envs)`` in front):

* the record at time ``t`` holds ``obs_t``, the action ``a_t`` chosen after seeing ``obs_t``, the reward ``r_t``
  it earned, and whatever else the agent needs (``dt_t``, the encoder state ``h_{t-1}``, ...): any pytree of
  arrays, fixed at :func:`replay_init` by one example record;
* an episode's final observation is a record of its own (its action and reward are unused) and the next record
  the caller adds with ``first=True`` starts the new episode.

A window of ``length`` records ``t .. t+length-1`` of one stream is *valid* iff all its records are in the
buffer (written and not yet overwritten, so it never straddles the write position: the oldest record is never
read after the newest) and no record at window positions ``lead+1 .. length-1`` has ``first`` set. With
``lead = 0`` (the default) only position 0 may start an episode, so an episode's final observation can only be
the last record of a window; for a horizon ``H`` model-learning window (``H + 1`` observations, ``H`` actions
and rewards) use ``length = H + 1`` and ignore the last record's action and reward; with burn-in ``T`` use
``length = T + H + 1``, and ``lead = T`` lets the burn-in reach back past the episode's start (the sampled
``first`` flags say where the agent restarts its state), so that the first ``T`` records of every episode are
learning steps too.

Sampling is exact and uniform over all valid windows: per call it builds the mask of valid window *ends*
(one comparison per slot, thanks to ``ep_step``, the number of earlier records of the same episode that the
stream wrote before each record, kept up to date by :func:`replay_add`), takes its cumulative sum and
``searchsorted``s ``batch_size`` uniform ranks into it: ``O(capacity * num_envs)`` vectorised work plus
``O(batch_size * log(capacity * num_envs))``, no per-sample scan over the buffer and no rejection loop.
The binary search is unrolled (``method="scan_unrolled"``): XLA's while loop costs a kernel launch and a
device-to-host check per step. Measured on one H200 (jitted call from the host, dispatch included, B = 256,
length 43, 88 floats per record): 0.10-0.20 ms per call for 1e5 to 1e6 slots, one seed or four vmapped
(0.6-0.8 ms with the while-loop search); ``replay_add`` 0.06-0.14 ms.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

PyTree = Any


@struct.dataclass
class ReplayState:
    """Buffer contents and bookkeeping (a pytree; stack it over seeds with ``vmap``).

    Attributes:
        fields: the records, the example record's pytree with leaves ``(capacity, num_envs, *shape)``.
        first: ``(capacity, num_envs)`` bool, the record starts an episode.
        ep_step: ``(capacity, num_envs)`` int32, number of earlier records of the same episode written before
            this one (saturating at ``capacity``; ``-1`` in never-written slots).
        pos: ``()`` int32, the slot the next :func:`replay_add` writes (the same for all streams).
        count: ``()`` int32, number of written slots per stream, ``min(adds so far, capacity)``.
    """

    fields: PyTree
    first: jax.Array
    ep_step: jax.Array
    pos: jax.Array
    count: jax.Array

    @property
    def capacity(self) -> int:
        """Time slots per stream (static; also correct on a seed-stacked state)."""
        return self.first.shape[-2]

    @property
    def num_envs(self) -> int:
        """Number of parallel environment streams (static)."""
        return self.first.shape[-1]


def _check_positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    return value


def replay_init(example_record: PyTree, capacity: int, num_envs: int = 1) -> ReplayState:
    """Allocate an empty buffer.

    Args:
        example_record: one record (no env axis), e.g. ``{"obs": (d,), "action": (a,), "reward": (), "dt": ()}``
            arrays or ``jax.ShapeDtypeStruct``s; only shapes and dtypes are used.
        capacity: time slots per stream (static int >= 1).
        num_envs: parallel streams (static int >= 1).

    Returns:
        A :class:`ReplayState` with zero-filled fields of shape ``(capacity, num_envs, *leaf.shape)``.
    """
    capacity = _check_positive_int("capacity", capacity)
    num_envs = _check_positive_int("num_envs", num_envs)
    leaves = jax.tree_util.tree_leaves(example_record)
    if not leaves:
        raise ValueError(f"example_record must contain at least one array, got {example_record!r}")
    fields = jax.tree_util.tree_map(
        lambda x: jnp.zeros((capacity, num_envs, *jnp.shape(x)), jnp.result_type(x)), example_record
    )
    return ReplayState(
        fields=fields,
        first=jnp.zeros((capacity, num_envs), bool),
        ep_step=jnp.full((capacity, num_envs), -1, jnp.int32),
        pos=jnp.zeros((), jnp.int32),
        count=jnp.zeros((), jnp.int32),
    )


def replay_add(state: ReplayState, record_batch: PyTree, first: jax.Array) -> ReplayState:
    """Write one time step of all streams at the write position, overwriting the oldest slot when full.

    Args:
        state: the buffer.
        record_batch: the example record's pytree with leaves ``(num_envs, *shape)``; leaves are cast to the
            buffer's dtypes (shapes and the tree structure must match exactly, else ``ValueError``).
        first: ``(num_envs,)`` bool, the record starts an episode (after a reset).

    Returns:
        The new state (jittable; no Python control flow on values).
    """
    cap, n_env = state.capacity, state.num_envs
    buf_def = jax.tree_util.tree_structure(state.fields)
    rec_def = jax.tree_util.tree_structure(record_batch)
    if rec_def != buf_def:
        raise ValueError(f"record_batch structure {rec_def} does not match the buffer's {buf_def}")
    for path, buf, x in zip(
        (jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(state.fields)[0]),
        jax.tree_util.tree_leaves(state.fields),
        jax.tree_util.tree_leaves(record_batch),
        strict=True,
    ):
        if jnp.shape(x) != buf.shape[1:]:
            raise ValueError(
                f"record_batch leaf {path or '<root>'} has shape {jnp.shape(x)}, expected {buf.shape[1:]} "
                f"(num_envs={n_env} first, then the example record's shape)"
            )
    first = jnp.asarray(first)
    if first.shape != (n_env,):
        raise ValueError(f"first has shape {first.shape}, expected ({n_env},)")
    first = first.astype(bool)
    pos = state.pos
    prev = state.ep_step[(pos - 1) % cap]
    ep_step = jnp.where(first, 0, jnp.minimum(prev + 1, cap)).astype(jnp.int32)
    fields = jax.tree_util.tree_map(
        lambda buf, x: buf.at[pos].set(jnp.asarray(x, buf.dtype)), state.fields, record_batch
    )
    return state.replace(
        fields=fields,
        first=state.first.at[pos].set(first),
        ep_step=state.ep_step.at[pos].set(ep_step),
        pos=(pos + 1) % cap,
        count=jnp.minimum(state.count + 1, cap),
    )


def replay_size(state: ReplayState) -> jax.Array:
    """Number of written time slots per stream, ``()`` int32 (``num_envs`` times as many records)."""
    return state.count


def _check_length(state: ReplayState, length: Any) -> int:
    length = _check_positive_int("length", length)
    if length > state.capacity:
        raise ValueError(f"length={length} exceeds capacity={state.capacity}")
    return length


def _check_lead(lead: Any, length: int) -> int:
    if isinstance(lead, bool) or not isinstance(lead, int) or not 0 <= lead < length:
        raise ValueError(f"lead must be an int in [0, length - 1] = [0, {length - 1}], got {lead!r}")
    return lead


def _valid_ends(state: ReplayState, length: int, lead: int = 0) -> jax.Array:
    """``(capacity, num_envs)`` bool: a valid window of ``length`` records (whose first ``lead`` may precede
    its episode) ends at this slot.

    The slot's age rank ``j`` (0 = oldest written slot) must satisfy ``length-1 <= j < count`` (the whole
    window is written and not overwritten), and ``ep_step >= length-1-lead`` (no ``first`` after position
    ``lead``: ``ep_step`` counts back to the latest ``first``, which lies at or before position ``lead``).
    Never-written slots have ``ep_step = -1``, so ``rank < count`` is implied; it stays as a guard for
    hand-built states.
    """
    cap = state.capacity
    oldest = (state.pos - state.count) % cap
    rank = (jnp.arange(cap, dtype=jnp.int32) - oldest) % cap
    in_buffer = (rank >= length - 1) & (rank < state.count)
    return in_buffer[:, None] & (state.ep_step >= length - 1 - lead)


def replay_num_windows(state: ReplayState, length: int, lead: int = 0) -> jax.Array:
    """Number of valid windows of ``length`` records (``lead``: as :func:`replay_sample`) over all streams,
    ``()`` int32."""
    length = _check_length(state, length)
    return jnp.sum(_valid_ends(state, length, _check_lead(lead, length)), dtype=jnp.int32)


def replay_sample(state: ReplayState, key: jax.Array, batch_size: int, length: int,
                  lead: int = 0) -> tuple[PyTree, jax.Array, jax.Array]:
    """Draw ``batch_size`` windows of ``length`` consecutive records, uniformly (with replacement) among all valid.

    Args:
        state: the buffer.
        key: PRNG key.
        batch_size: windows per call (static int >= 1).
        length: records per window (static, ``1 <= length <= capacity``).
        lead: (static, ``0 <= lead < length``) the first ``lead`` records of a window may belong to the episode
            before the one its last ``length - lead`` records lie in (a burn-in that reaches back past the
            episode's start, the agent restarting its state at the ``first`` record); 0: no window crosses an
            episode start.

    Returns:
        ``(records, first, valid)``: ``records`` is the fields pytree with leaves ``(length, batch_size,
        *shape)`` (time-major); ``first`` is ``(length, batch_size)`` bool, the records that start an episode
        (only at positions ``0 .. lead``); ``valid`` is ``(batch_size,)`` bool, all True unless the buffer holds
        no valid window (check :func:`replay_num_windows`), in which case the records are meaningless and all
        False: use it as a loss weight to make updates on an empty buffer no-ops.
    """
    batch_size = _check_positive_int("batch_size", batch_size)
    length = _check_length(state, length)
    lead = _check_lead(lead, length)
    cap, n_env = state.capacity, state.num_envs
    if cap * n_env >= 2**31:
        raise ValueError(f"capacity*num_envs={cap * n_env} overflows the int32 window count")
    cum = jnp.cumsum(_valid_ends(state, length, lead).reshape(-1), dtype=jnp.int32)
    total = cum[-1]
    rank = jax.random.randint(key, (batch_size,), 0, jnp.maximum(total, 1), dtype=jnp.int32)
    # The rank-th valid end (0-based) is the first flat slot whose inclusive count exceeds rank.
    flat = jnp.searchsorted(cum, rank, side="right", method="scan_unrolled").astype(jnp.int32)
    flat = jnp.minimum(flat, cap * n_env - 1)
    end_slot, env = flat // n_env, flat % n_env
    slots = (end_slot[None, :] - (length - 1) + jnp.arange(length, dtype=jnp.int32)[:, None]) % cap
    records = jax.tree_util.tree_map(lambda buf: buf[slots, env[None, :]], state.fields)
    valid = jnp.broadcast_to(total > 0, (batch_size,))
    return records, state.first[slots, env[None, :]], valid


def replay_capacity_for(env_steps: int, action_repeat: int, num_envs: int, episode_decisions: int = 500) -> int:
    """Slots per stream that hold a whole run of ``env_steps`` environment steps without overwriting.

    Each stream makes ``ceil(env_steps / action_repeat / num_envs)`` decisions (one record each) and writes one
    extra record (the final observation) per episode of ``episode_decisions`` decisions.
    """
    for name, v in (("env_steps", env_steps), ("action_repeat", action_repeat), ("num_envs", num_envs)):
        _check_positive_int(name, v)
    decisions = math.ceil(env_steps / (action_repeat * num_envs))
    return decisions + math.ceil(decisions / _check_positive_int("episode_decisions", episode_decisions))
