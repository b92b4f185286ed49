"""benchmarks/common.py's ``tree_digest``: the fingerprint ``train_throughput.py`` records of a training chunk's
output, to show whether two runs computed the same numbers (on a GPU, runs under deterministic ops: run 34)."""

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from common import time_call, tree_digest  # noqa: E402


def tree(x=1.0):
    return {"params": {"w": jnp.arange(6.0).reshape(2, 3) * x, "b": jnp.zeros((3,))},
            "key": jax.random.key(3), "step": jnp.array(7, dtype=jnp.int32)}


def test_equal_trees_share_a_digest_and_any_change_moves_it():
    base = tree_digest(tree())
    assert base == tree_digest(tree()) and len(base) == 64
    assert tree_digest(tree(1.0 + 1e-7)) != base  # one ulp-scale change in one leaf
    changed_key = {**tree(), "key": jax.random.key(4)}
    assert tree_digest(changed_key) != base  # typed PRNG keys count by their key data
    same_bytes_other_dtype = {**tree(), "step": jnp.array(7, dtype=jnp.uint32)}
    assert tree_digest(same_bytes_other_dtype) != base
    reshaped = {**tree(), "params": {"w": jnp.arange(6.0).reshape(3, 2), "b": jnp.zeros((3,))}}
    assert tree_digest(reshaped) != base


def test_time_call_returns_the_last_result_only_when_asked():
    """``train_throughput.time_chunk`` digests the timed calls' own result instead of running the chunk again."""
    calls = []

    def fn(x):
        calls.append(1)
        return x * len(calls)

    timed = time_call(fn, jnp.arange(3.0), repeats=2, keep_output=True)
    assert len(calls) == 3 and len(timed["times_s"]) == 2  # the first (compiling) call and the two timed ones
    assert timed["output"].tolist() == [0.0, 3.0, 6.0]  # the last call's result
    assert "output" not in time_call(fn, jnp.arange(3.0), repeats=1)
