"""benchmarks/common.py's ``tree_digest``: the fingerprint ``train_throughput.py`` records of a training chunk's
output, to show whether two runs computed the same numbers (on a GPU, runs under deterministic ops: run 34)."""

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from common import tree_digest  # noqa: E402


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
