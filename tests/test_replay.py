"""Replay buffer: windows never cross episodes, unwritten slots or the ring's write position; exact uniform
sampling; jit/vmap over seeds; extra pytree fields round-trip; argument checks."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc.replay import (
    replay_add,
    replay_capacity_for,
    replay_init,
    replay_num_windows,
    replay_sample,
    replay_size,
)

H = 4


def example_record():
    return {
        "obs": jnp.zeros((3,), jnp.float32),
        "reward": jnp.zeros((), jnp.float32),
        "t": jnp.zeros((), jnp.int32),
        "ep": jnp.zeros((), jnp.int32),
        "env": jnp.zeros((), jnp.int32),
        "written": jnp.zeros((), bool),
        "first": jnp.zeros((), bool),
        "aux": {"h": jnp.zeros((H,), jnp.float32)},
    }


def make_stream(rng, n, num_envs, max_ep=None, tag=0):
    """Records (leaves (n, num_envs, ...)) of random-length episodes; max_ep=None: one episode per stream."""
    first = np.zeros((n, num_envs), bool)
    ep = np.zeros((n, num_envs), np.int32)
    next_id = 1
    for e in range(num_envs):
        t = 0
        while t < n:
            ep_len = n if max_ep is None else int(rng.integers(1, max_ep + 1))
            first[t, e] = True
            ep[t : t + ep_len, e] = next_id
            next_id += 1
            t += ep_len
    t_idx = np.broadcast_to(np.arange(n, dtype=np.int32)[:, None], (n, num_envs))
    recs = {
        "obs": rng.normal(size=(n, num_envs, 3)).astype(np.float32) + tag,
        "reward": rng.normal(size=(n, num_envs)).astype(np.float32),
        "t": t_idx.copy(),
        "ep": ep,
        "env": np.broadcast_to(np.arange(num_envs, dtype=np.int32), (n, num_envs)).copy(),
        "written": np.ones((n, num_envs), bool),
        "first": first,
        "aux": {"h": rng.normal(size=(n, num_envs, H)).astype(np.float32)},
    }
    return recs, first


@jax.jit
def add_all(state, recs, first):
    return jax.lax.scan(lambda s, x: (replay_add(s, *x), None), state, (recs, first))[0]


def filled(capacity, num_envs, n, max_ep=None, seed=0):
    recs, first = make_stream(np.random.default_rng(seed), n, num_envs, max_ep)
    return add_all(replay_init(example_record(), capacity, num_envs), recs, first), recs


def reference_windows(first, n, capacity, length, lead=0):
    """Set of valid (start time, env) by brute force over the stream's last min(n, capacity) records: no episode
    start after position ``lead``."""
    lo = max(0, n - capacity)
    return {
        (s, e)
        for e in range(first.shape[1])
        for s in range(lo, n - length + 1)
        if not first[s + 1 + lead : s + length, e].any()
    }


sample = jax.jit(replay_sample, static_argnums=(2, 3))


def check_windows(records, valid, recs, n, capacity, length):
    """Every window: one episode, consecutive times, written and not overwritten; returns (t0, env) pairs."""
    r = jax.tree_util.tree_map(np.asarray, records)
    assert np.asarray(valid).all()
    assert r["t"].shape[0] == length
    assert r["written"].all(), "read an unwritten slot"
    assert (r["ep"] == r["ep"][:1]).all(), "window crosses an episode boundary"
    assert (np.diff(r["t"], axis=0) == 1).all(), "window is not consecutive in time (straddles the write position)"
    assert (r["t"][0] >= n - capacity).all() and (r["t"][-1] < n).all()
    assert not r["first"][1:].any()
    return set(zip(r["t"][0].tolist(), r["env"][0].tolist(), strict=True))


@pytest.mark.parametrize("n", [40, 64, 203])  # partially full, exactly full, wrapped several times
def test_windows_never_cross_episodes_or_write_position(n):
    capacity, num_envs, length = 64, 3, 5
    state, recs = filled(capacity, num_envs, n, max_ep=12, seed=n)
    ref = reference_windows(recs["first"], n, capacity, length)
    assert int(replay_size(state)) == min(n, capacity)
    assert int(replay_num_windows(state, length)) == len(ref)
    records, _, valid = sample(state, jax.random.key(n), 512, length)
    got = check_windows(records, valid, recs, n, capacity, length)
    assert got <= ref


def test_wrap_without_episode_ends_uses_whole_ring():
    capacity, num_envs, length, n = 32, 2, 6, 3 * 32 + 7
    state, recs = filled(capacity, num_envs, n)
    assert int(replay_num_windows(state, length)) == num_envs * (capacity - length + 1)
    records, _, valid = sample(state, jax.random.key(1), 4000, length)
    got = check_windows(records, valid, recs, n, capacity, length)
    starts = {s for s, _ in got}
    assert min(starts) == n - capacity and max(starts) == n - length  # oldest and newest windows both reachable
    # same check with length == capacity: exactly one window per stream, the whole ring in time order
    records, _, _ = sample(state, jax.random.key(2), 8, capacity)
    np.testing.assert_array_equal(np.asarray(records["t"])[:, 0], np.arange(n - capacity, n))


def test_partially_full_and_empty():
    state = replay_init(example_record(), 50, 2)
    records, _, valid = sample(state, jax.random.key(0), 4, 1)
    assert not np.asarray(valid).any() and int(replay_num_windows(state, 1)) == 0
    state, recs = filled(50, 2, 7, max_ep=3, seed=3)
    assert int(replay_size(state)) == 7
    records, _, valid = sample(state, jax.random.key(0), 256, 2)
    check_windows(records, valid, recs, 7, 50, 2)
    # more than the episodes allow: no valid window of length 4 when episodes have <= 3 records
    assert int(replay_num_windows(state, 4)) == 0
    assert not np.asarray(sample(state, jax.random.key(0), 3, 4)[2]).any()


def test_sampling_is_uniform_over_valid_windows():
    capacity, num_envs, length, n = 24, 2, 3, 37
    state, recs = filled(capacity, num_envs, n, max_ep=7, seed=11)
    ref = sorted(reference_windows(recs["first"], n, capacity, length))
    assert int(replay_num_windows(state, length)) == len(ref) > 10
    draws = 40_000
    records, _, valid = sample(state, jax.random.key(5), draws, length)
    check_windows(records, valid, recs, n, capacity, length)
    keys = list(zip(np.asarray(records["t"][0]).tolist(), np.asarray(records["env"][0]).tolist(), strict=True))
    index = {w: i for i, w in enumerate(ref)}
    counts = np.bincount([index[k] for k in keys], minlength=len(ref))
    assert counts.min() > 0
    expected = draws / len(ref)
    chi2 = ((counts - expected) ** 2 / expected).sum()
    dof = len(ref) - 1
    assert chi2 < dof + 6 * np.sqrt(2 * dof), (chi2, dof)


def test_jit_vmap_over_seeds_independent_buffers():
    seeds, capacity, num_envs, length, n = 3, 20, 2, 4, 33
    streams = [make_stream(np.random.default_rng(s), n, num_envs, max_ep=5 + 4 * s, tag=100 * s) for s in range(seeds)]
    recs = jax.tree_util.tree_map(lambda *x: np.stack(x), *[r for r, _ in streams])
    first = np.stack([f for _, f in streams])
    init = jax.vmap(lambda _: replay_init(example_record(), capacity, num_envs))(jnp.arange(seeds))
    assert init.capacity == capacity and init.num_envs == num_envs
    state = jax.jit(jax.vmap(add_all))(init, recs, first)
    counts = jax.jit(jax.vmap(partial(replay_num_windows, length=length)))(state)
    keys = jax.random.split(jax.random.key(0), seeds)
    records, _, valid = jax.jit(jax.vmap(partial(replay_sample, batch_size=300, length=length)))(state, keys)
    for s, (rec_s, first_s) in enumerate(streams):
        ref = reference_windows(first_s, n, capacity, length)
        assert int(counts[s]) == len(ref)
        r_s = jax.tree_util.tree_map(lambda x, s=s: x[s], records)
        assert check_windows(r_s, valid[s], rec_s, n, capacity, length) <= ref
        assert (np.floor(np.asarray(r_s["obs"]).mean() / 100 + 0.5) == s), "window came from another seed's buffer"
    assert not np.array_equal(np.asarray(records["t"][0]), np.asarray(records["t"][1]))


@pytest.mark.parametrize("n", [40, 203])
def test_lead_lets_a_window_reach_back_past_its_episode_start(n):
    """``lead=L``: the last ``length - L`` records of a window lie in one episode, the first ``L`` may belong to
    the episode before; the sampled ``first`` flags are the records' own, set only at positions ``0 .. L``. Every
    window that a brute-force scan allows is drawn (and no other), so episodes' first records become reachable
    at every position past the lead."""
    capacity, num_envs, length, lead = 64, 3, 7, 3
    state, recs = filled(capacity, num_envs, n, max_ep=12, seed=n + 1)
    ref = reference_windows(recs["first"], n, capacity, length, lead)
    assert int(replay_num_windows(state, length, lead)) == len(ref) > len(reference_windows(recs["first"], n,
                                                                                          capacity, length))
    records, first, valid = jax.jit(replay_sample, static_argnums=(2, 3, 4))(state, jax.random.key(n), 20_000,
                                                                              length, lead)
    r = jax.tree_util.tree_map(np.asarray, records)
    first = np.asarray(first)
    assert np.asarray(valid).all() and r["written"].all() and (np.diff(r["t"], axis=0) == 1).all()
    np.testing.assert_array_equal(first, r["first"])  # the flags of the records drawn
    assert not first[lead + 1:].any() and first[1:lead + 1].any()  # starts inside the lead, and only there
    assert (r["ep"][lead:] == r["ep"][-1:]).all()  # the part after the lead is one episode
    got = set(zip(r["t"][0].tolist(), r["env"][0].tolist(), strict=True))
    assert got == ref


def test_extra_fields_round_trip_exactly():
    capacity, num_envs, length, n = 16, 3, 4, 40
    state, recs = filled(capacity, num_envs, n, max_ep=9, seed=7)
    records, _, valid = sample(state, jax.random.key(3), 200, length)
    check_windows(records, valid, recs, n, capacity, length)
    t, env = np.asarray(records["t"]), np.asarray(records["env"])
    for name in ("obs", "reward", "ep", "first"):
        np.testing.assert_array_equal(np.asarray(records[name]), recs[name][t, env])
    h = np.asarray(records["aux"]["h"])
    assert h.shape == (length, 200, H) and h.dtype == np.float32
    np.testing.assert_array_equal(h, recs["aux"]["h"][t, env])


def test_bad_arguments_raise_value_error():
    state = replay_init(example_record(), 8, 2)
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="length=9 exceeds capacity=8"):
        replay_sample(state, key, 4, 9)
    with pytest.raises(ValueError, match="length must be a positive int, got 0"):
        replay_num_windows(state, 0)
    with pytest.raises(ValueError, match="batch_size must be a positive int, got 0"):
        replay_sample(state, key, 0, 2)
    with pytest.raises(ValueError, match=r"lead must be an int in \[0, length - 1\] = \[0, 2\], got 3"):
        replay_sample(state, key, 4, 3, lead=3)
    with pytest.raises(ValueError, match="capacity must be a positive int, got 0"):
        replay_init(example_record(), 0, 1)
    with pytest.raises(ValueError, match="num_envs must be a positive int, got 1.5"):
        replay_init(example_record(), 4, 1.5)
    good = jax.tree_util.tree_map(lambda b: b[0], state.fields)
    bad = dict(good, obs=jnp.zeros((2, 4)))
    with pytest.raises(ValueError, match=r"\['obs'\] has shape \(2, 4\), expected \(2, 3\)"):
        replay_add(state, bad, jnp.zeros(2, bool))
    with pytest.raises(ValueError, match=r"shape \(3, 3\), expected \(2, 3\)"):
        replay_add(state, dict(good, obs=jnp.zeros((3, 3))), jnp.zeros(2, bool))
    with pytest.raises(ValueError, match="structure"):
        replay_add(state, {k: v for k, v in good.items() if k != "aux"}, jnp.zeros(2, bool))
    with pytest.raises(ValueError, match=r"first has shape \(3,\), expected \(2,\)"):
        replay_add(state, good, jnp.zeros(3, bool))
    replay_add(state, good, jnp.zeros(2, bool))  # the matching record is accepted


def test_capacity_for_budget():
    assert replay_capacity_for(200_000, 2, 1) == 100_000 + 200
    assert replay_capacity_for(200_000, 2, 4) == 25_000 + 50
