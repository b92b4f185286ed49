"""``policy.npz``: the agent's parameters exported beside the checkpoints, restored into a fresh agent state."""

from __future__ import annotations

import os

import jax
import numpy as np
import pytest

from lnnmpc.agents.registry import make_agent
from lnnmpc.train.config import ConfigError
from lnnmpc.train.policy_file import POLICY_FILE, policy_step, restore_policy, save_policy


@pytest.fixture(scope="module")
def agent_states():
    """Two seed-batched (2 seeds) initialisations of a small TD-MPC2 agent on cartpole's shapes."""
    agent = make_agent("tdmpc2", 5, 1, model_size=1, small=True)
    init = jax.jit(jax.vmap(agent.init))
    return init(jax.random.split(jax.random.key(0), 2)), init(jax.random.split(jax.random.key(1), 2))


def test_policy_round_trip_keeps_params_and_takes_the_rest_from_the_fresh_state(agent_states, tmp_path):
    trained, fresh = agent_states
    trained = trained.replace(updates=trained.updates + 7)
    assert policy_step(str(tmp_path)) is None
    path = save_policy(str(tmp_path), 12_345, trained)
    assert path.endswith(POLICY_FILE) and sorted(p.name for p in tmp_path.iterdir()) == [POLICY_FILE]  # no temp
    assert policy_step(str(tmp_path)) == 12_345
    restored = restore_policy(str(tmp_path), fresh)
    same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))
    assert same(restored.params, trained.params) and not same(restored.params, fresh.params)
    assert same(restored.scale, trained.scale) and np.array_equal(restored.updates, trained.updates)
    assert same(restored.target_q, fresh.target_q) and same(restored.model_opt, fresh.model_opt)
    with np.load(path) as archive:  # readable without lnnmpc: key paths and (seeds, ...) leaves
        names = [str(p) for p in archive["paths"]]
        assert names[0].startswith("['params'][") and archive["leaf_0"].shape[0] == 2


def test_policy_of_another_agent_is_refused_naming_the_leaf(agent_states, tmp_path):
    trained, _ = agent_states
    save_policy(str(tmp_path), 100, trained)
    one_seed = jax.tree.map(lambda x: x[:1], trained)
    with pytest.raises(ConfigError, match=r"policy.npz: \['params'\]\[.*\] is float32\[2, .*the run's agent has "
                                          r"float32\[1, "):
        restore_policy(str(tmp_path), one_seed)
    wider = make_agent("tdmpc2", 7, 1, model_size=1, small=True)
    with pytest.raises(ConfigError, match="is float32"):
        restore_policy(str(tmp_path), jax.vmap(wider.init)(jax.random.split(jax.random.key(0), 2)))
    with pytest.raises(ConfigError, match="has no policy.npz"):
        restore_policy(str(tmp_path / "elsewhere"), trained)


def test_evaluation_snapshots_are_kept_apart_listed_by_step_and_restored_from_their_own_file(agent_states, tmp_path):
    """``policies/policy-<step>.npz`` (``eval_policies``): each step's file holds that step's parameters;
    ``policy_path`` prefers ``policy.npz`` where it is of the asked step and names no file for a step without one."""
    from lnnmpc.train.policy_file import policy_path, save_policy_snapshot, snapshot_path, snapshot_steps

    first, second = agent_states
    run = str(tmp_path)
    assert snapshot_steps(run) == [] and policy_path(run, 600) is None
    save_policy_snapshot(run, 1_200, second)
    save_policy_snapshot(run, 600, first)
    save_policy(run, 1_200, second)
    (tmp_path / "policies" / "policy-600.npz.tmp-1").write_bytes(b"")  # a killed write's leftover: not a step
    (tmp_path / "policies" / "notes.txt").write_text("")
    assert snapshot_steps(run) == [600, 1_200]
    assert policy_path(run, 1_200) == os.path.join(run, POLICY_FILE)
    assert policy_path(run, 600) == snapshot_path(run, 600) == os.path.join(run, "policies", "policy-600.npz")
    assert policy_path(run, 900) is None
    leaves = lambda tree: [np.asarray(x) for x in jax.tree.leaves(tree)]
    for step, state in ((600, first), (1_200, second)):
        restored = restore_policy(run, second if step == 600 else first, policy_path(run, step))
        assert all(np.array_equal(x, y) for x, y in zip(leaves(restored.params), leaves(state.params), strict=True))
        with np.load(snapshot_path(run, step)) as archive:
            assert int(archive["step"]) == step
    with pytest.raises(ConfigError, match=r"has no policies/policy-900.npz"):
        restore_policy(run, first, snapshot_path(run, 900))
