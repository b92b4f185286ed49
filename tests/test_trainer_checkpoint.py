"""Checkpoints: an interrupted write is ignored (the previous checkpoint is used), the newest k are kept, abstract
restore targets (for evaluation) work, and PRNG keys survive."""

from __future__ import annotations

import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.train.checkpoint import all_steps, latest_step, restore_checkpoint, save_checkpoint


def _state(value: float):
    return {"w": jnp.full((3, 4), value), "key": jax.random.key(int(value)), "empty": jnp.zeros((0, 2))}


def test_interrupted_write_is_ignored_and_the_previous_checkpoint_used(tmp_path):
    run = str(tmp_path)
    save_checkpoint(run, 100, _state(1.0), {"env_steps": 100})
    save_checkpoint(run, 200, _state(2.0), {"env_steps": 200})
    # What a process killed while writing step 300 leaves: orbax's temporary folder, never renamed.
    folder = os.path.join(run, "checkpoints")
    shutil.copytree(os.path.join(folder, "200"), os.path.join(folder, "300.orbax-checkpoint-tmp-1234567"))
    os.remove(next(os.path.join(root, f) for root, _, files in
                   os.walk(os.path.join(folder, "300.orbax-checkpoint-tmp-1234567")) for f in files))
    assert latest_step(run) == 200 and all_steps(run) == [100, 200]
    state, host = restore_checkpoint(run, latest_step(run), _state(0.0))
    assert host == {"env_steps": 200}
    np.testing.assert_array_equal(state["w"], np.full((3, 4), 2.0))
    np.testing.assert_array_equal(jax.random.key_data(state["key"]), jax.random.key_data(jax.random.key(2)))
    # The next save goes through and counts as newest.
    save_checkpoint(run, 300, _state(3.0), {"env_steps": 300})
    assert latest_step(run) == 300


def test_keeps_the_newest_checkpoints_and_restores_into_abstract_targets(tmp_path):
    run = str(tmp_path)
    for step in (1, 2, 3, 4):
        save_checkpoint(run, step, _state(float(step)), {"env_steps": step}, keep=2)
    assert all_steps(run) == [3, 4]
    abstract = jax.eval_shape(lambda: _state(0.0))
    state, _ = restore_checkpoint(run, 3, abstract)
    np.testing.assert_array_equal(state["w"], np.full((3, 4), 3.0))
    assert state["empty"].shape == (0, 2)
    np.testing.assert_array_equal(jax.random.key_data(state["key"]), jax.random.key_data(jax.random.key(3)))


def test_abstract_targets_keep_their_sharding_keys_included(tmp_path):
    """A resumed sharded run restores into its state's abstract shapes (``SeedPlacement.abstract``): every leaf,
    PRNG keys included, must come back with the target's sharding (a default-device array is refused by the
    sharded programs)."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    run = str(tmp_path)
    state = {"w": jnp.arange(8.0).reshape(2, 4), "key": jax.random.split(jax.random.key(5), 2),
             "empty": jnp.zeros((2, 0))}
    save_checkpoint(run, 1, state, {"env_steps": 1})
    sharding = NamedSharding(Mesh(np.asarray(jax.devices()[:1]), ("seeds",)), PartitionSpec("seeds"))
    abstract = jax.tree_util.tree_map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sharding),
                                      jax.eval_shape(lambda: state))
    restored, _ = restore_checkpoint(run, 1, abstract)
    assert {name: leaf.sharding for name, leaf in restored.items()} == dict.fromkeys(state, sharding)
    np.testing.assert_array_equal(restored["w"], state["w"])
    np.testing.assert_array_equal(jax.random.key_data(restored["key"]), jax.random.key_data(state["key"]))
