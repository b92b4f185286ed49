"""Initial-state distributions against dm_control's own resets (moments over many episodes)."""

from __future__ import annotations

import dm_reference
import jax
import numpy as np
import pytest

from lnnmpc import envs

N_DM, N_MJX = 600, 6000


@pytest.mark.parametrize("task", ["cartpole-swingup", "cartpole-balance", "acrobot-swingup", "walker-run"])
def test_initial_state_moments_match_dm_control(task):
    ref_qpos, ref_qvel = dm_reference.initial_states(task, N_DM, seed=0)
    env = envs.make(task)
    keys = jax.random.split(jax.random.key(0), N_MJX)
    qpos, qvel = (np.asarray(x, np.float64) for x in jax.jit(jax.vmap(env.initial_qpos_qvel))(keys))
    for name, ref, ours in (("qpos", ref_qpos, qpos), ("qvel", ref_qvel, qvel)):
        assert ours.shape[1:] == ref.shape[1:], name
        ref_mean, ref_std = ref.mean(0), ref.std(0)
        our_mean, our_std = ours.mean(0), ours.std(0)
        constant = ref_std < 1e-12
        # Dimensions dm_control leaves fixed (e.g. walker rootz/rootx, its qvel) are fixed here too.
        np.testing.assert_allclose(our_std[constant], 0.0, atol=1e-6, err_msg=name)
        np.testing.assert_allclose(our_mean[constant], ref_mean[constant], atol=1e-6, err_msg=name)
        varying = ~constant
        stderr = np.sqrt(ref_std**2 / N_DM + our_std**2 / N_MJX)[varying]
        assert np.all(np.abs(our_mean[varying] - ref_mean[varying]) < 5 * stderr), (name, our_mean, ref_mean)
        # Standard deviations within sampling error (~3% for 600 samples; allow 5 sigma-ish).
        np.testing.assert_allclose(our_std[varying], ref_std[varying], rtol=0.15, err_msg=name)
        # Shapes of the distributions agree: deciles within sampling error (~0.1 std for 600 samples).
        deciles = np.linspace(0.1, 0.9, 9)
        ref_q, our_q = np.quantile(ref, deciles, axis=0), np.quantile(ours, deciles, axis=0)
        assert np.all(np.abs(ref_q - our_q)[:, varying] < 0.35 * ref_std[varying]), (name, ref_q, our_q)
