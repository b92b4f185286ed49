"""LNN-TD-MPC2's latent heads (SimNorm over the encoder state, with the observation read beside it, with a hidden
layer) against float64 numpy, and their validation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lnn_helpers import ACT, OBS, B, quick_jit, tiny, window


def test_simnorm_latent_head_puts_latents_and_predictions_on_simplices():
    """``latent_head="simnorm"``: z = SimNorm(LayerNorm(W h + b)) in training, acting and the planner's
    transitions, ``latent_size`` wide (12 here, the encoder state 8); the head trains at the encoder's learning
    rate; only *-zp-det agents take it."""
    from lnnmpc.agents.registry import acting_latent

    agent = tiny("cfc-zp-det", latent_head="simnorm", simnorm_dim=4, latent_size=12)
    state = quick_jit(agent.init)(jax.random.key(0))
    assert set(state.params) >= {"encoder", "latent_head", "predictor"}
    batch, T = window(agent), agent.config.burn_in
    _, (zs, _) = quick_jit(lambda p: agent.world_model_loss(p, state.target_q, batch, jax.random.key(1)))(
        state.params)
    on_simplices = lambda z: (np.all(np.asarray(z) >= 0)
                              and np.allclose(np.asarray(z).reshape(*z.shape[:-1], -1, 4).sum(-1), 1, atol=1e-5))
    assert zs.shape == (agent.config.horizon + 1, B, 12) and on_simplices(zs)
    # z is the head on the encoder states of the same window (burn-in then the learning steps) ...
    h_T = agent.encode_sequence(state.params, batch["h_prev"][0], batch["obs"][:T], batch["prev_action"][:T],
                                batch["dt"][:T])[-1]
    hs = agent.encode_sequence(state.params, h_T, batch["obs"][T:], batch["prev_action"][T:], batch["dt"][T:])
    assert hs.shape[-1] == 8 and not on_simplices(hs)
    np.testing.assert_allclose(np.asarray(zs), np.asarray(agent.latent_of(state.params, hs, batch["obs"][T:])),
                               rtol=1e-5, atol=1e-6)
    # ... the planner's transition predicts a latent on the simplices too, and the actor plans from the head's z.
    z_next = agent._apply(state.params, zs[0], batch["action"][T], method="transition")
    assert z_next.shape == (B, 12) and on_simplices(z_next)
    _, carry = agent.act(state, agent.initial_carry(), batch["obs"][0, 0], batch["dt"][0, 0], jax.random.key(2),
                         explore=False, first_step=jnp.array(True))
    z_act = acting_latent(agent, state, carry, batch["obs"][0, 0])
    assert z_act.shape == (12,) and on_simplices(z_act)
    z_head = agent.latent_of(state.params, carry.h, batch["obs"][0, 0])
    np.testing.assert_allclose(np.asarray(z_act), np.asarray(z_head), rtol=1e-6)
    # Adam's first step moves every parameter by its group's learning rate: the head's is the encoder's (× 0.3).
    ones = jax.tree_util.tree_map(jnp.ones_like, state.params)
    step, _ = agent.model_tx.update(ones, agent.model_tx.init(state.params), state.params)
    lr = agent.config.lr
    for group, scale in (("encoder", 0.3), ("latent_head", 0.3), ("predictor", 1.0)):
        for leaf in jax.tree_util.tree_leaves(step[group]):
            np.testing.assert_allclose(np.asarray(leaf), -lr * scale, rtol=1e-3, err_msg=group)
    assert not {"model.simnorm_dim", "model.latent_size"} & agent.config.inactive_fields()
    assert {"model.simnorm_dim", "model.latent_size"} <= tiny("cfc-zp-det").config.inactive_fields()
    with pytest.raises(ValueError, match=r"latent_head='simnorm' needs a self-predictive deterministic agent "
                                         r"\(\*-zp-det\), got objective='op', stochastic=False"):
        tiny("cfc-op-det", latent_head="simnorm")
    with pytest.raises(ValueError, match=r"objective='zp', stochastic=True"):
        tiny("ltc-zp-stoch", latent_head="simnorm")
    with pytest.raises(ValueError, match=r"latent size divisible by simnorm_dim, got hidden_size=8, simnorm_dim=3"):
        tiny("cfc-zp-det", latent_head="simnorm", simnorm_dim=3)
    with pytest.raises(ValueError, match=r"latent size divisible by simnorm_dim, got latent_size=10, simnorm_dim=4"):
        tiny("cfc-zp-det", latent_head="simnorm", simnorm_dim=4, latent_size=10)
    with pytest.raises(ValueError, match=r"latent_size=16 needs latent_head='simnorm': without a head the latent is "
                                         r"the encoder state \(hidden_size=8\)"):
        tiny("cfc-zp-det", latent_size=16)
    with pytest.raises(ValueError, match=r"latent_size=-8 is invalid; expected an integer >= 0"):
        tiny("cfc-zp-det", latent_head="simnorm", latent_size=-8)
    with pytest.raises(ValueError, match=r"latent_head='ln' is not supported; allowed values: \['none', 'simnorm'\]"):
        tiny("cfc-zp-det", latent_head="ln")


def np_latent_head(params, h, obs, group: int) -> np.ndarray:
    """float64 numpy SimNorm latent head on [h, symlog(obs)] (on h alone when ``obs`` is None): [Dense -> LayerNorm
    -> Mish] -> Dense -> LayerNorm -> SimNorm (groups of ``group``), with the hidden layer when ``params`` has one."""
    p = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), params)
    x = np.asarray(h, np.float64)
    if obs is not None:
        o = np.asarray(obs, np.float64)
        x = np.concatenate([x, np.sign(o) * np.log1p(np.abs(o))], axis=-1)

    def dense_norm(x, i):
        x = x @ p[f"Dense_{i}"]["kernel"] + p[f"Dense_{i}"]["bias"]
        x = (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + 1e-5)
        return x * p[f"LayerNorm_{i}"]["scale"] + p[f"LayerNorm_{i}"]["bias"]

    if "Dense_1" in p:
        x = dense_norm(x, 0)
        x = x * np.tanh(np.log1p(np.exp(x)))  # Mish
    x = dense_norm(x, 1 if "Dense_1" in p else 0)
    g = x.reshape(*x.shape[:-1], -1, group)
    g = np.exp(g - g.max(-1, keepdims=True))
    return (g / g.sum(-1, keepdims=True)).reshape(x.shape)


def test_latent_obs_skip_head_reads_state_and_observation():
    """``latent_obs_skip``: z = SimNorm(LayerNorm(W [h, transform(o)] + b)) against float64 numpy, for the window's
    latents (each state with the observation it has just read), the actor's and the one-observation encoder's;
    only with a SimNorm head."""
    from lnnmpc.agents.registry import acting_latent

    agent = tiny("cfc-zp-det", latent_head="simnorm", simnorm_dim=4, latent_size=12, latent_obs_skip="true",
                 input_transform="symlog")
    state = quick_jit(agent.init)(jax.random.key(0))
    assert state.params["latent_head"]["Dense_0"]["kernel"].shape == (8 + OBS, 12)
    reference = lambda h, obs: np_latent_head(state.params["latent_head"], h, obs, 4)

    batch, T = window(agent), agent.config.burn_in
    _, (zs, _) = quick_jit(lambda p: agent.world_model_loss(p, state.target_q, batch, jax.random.key(1)))(
        state.params)
    h_T = agent.encode_sequence(state.params, batch["h_prev"][0], batch["obs"][:T], batch["prev_action"][:T],
                                batch["dt"][:T])[-1]
    hs = agent.encode_sequence(state.params, h_T, batch["obs"][T:], batch["prev_action"][T:], batch["dt"][T:])
    np.testing.assert_allclose(np.asarray(zs), reference(hs, batch["obs"][T:]), rtol=1e-4, atol=1e-6)
    # The observation moves the latent at a fixed state (the skip is live).
    moved = agent.latent_of(state.params, hs[0], batch["obs"][T] + 1.0)
    assert float(jnp.abs(moved - zs[0]).max()) > 1e-3
    obs, dt = batch["obs"][0, 0], batch["dt"][0, 0]
    _, carry = agent.act(state, agent.initial_carry(), obs, dt, jax.random.key(2), explore=False,
                         first_step=jnp.array(True))
    np.testing.assert_allclose(np.asarray(acting_latent(agent, state, carry, obs)), reference(carry.h, obs),
                               rtol=1e-4, atol=1e-6)
    # TD-MPC2's per-observation encode: the head on the one-observation history's state and that observation.
    h1 = agent._apply(state.params, jnp.zeros((1, 8)), obs[None], jnp.zeros((1, ACT)), jnp.ones((1,)),
                      method="encode_step")
    np.testing.assert_allclose(np.asarray(agent._apply(state.params, obs[None], method="encode")),
                               reference(h1, obs[None]), rtol=1e-4, atol=1e-6)
    assert "model.latent_obs_skip" not in agent.config.inactive_fields()
    assert "model.latent_obs_skip" in tiny("cfc-zp-det").config.inactive_fields()
    with pytest.raises(ValueError, match=r"latent_obs_skip=True needs latent_head='simnorm': without a head the "
                                         r"latent is the encoder state \(hidden_size=8\)"):
        tiny("cfc-zp-det", latent_obs_skip=True)
    with pytest.raises(ValueError, match=r"the latent needs the observation the state has read"):
        agent._apply(state.params, hs[0], method="latent")


def test_latent_head_hidden_layer_as_tdmpc2_encoder():
    """``latent_head_hidden=W``: Dense -> LayerNorm -> Mish (W wide) before the head's output layer, against float64
    numpy, with and without the observation skip; only with a SimNorm head."""
    h = 0.5 * jnp.tanh(jax.random.normal(jax.random.key(3), (B, 8)))
    obs = 3.0 * jax.random.normal(jax.random.key(4), (B, OBS))
    for skip in (False, True):
        agent = tiny("cfc-zp-det", latent_head="simnorm", simnorm_dim=4, latent_size=12, latent_head_hidden=6,
                     latent_obs_skip=skip, input_transform="symlog")
        params = quick_jit(agent.init)(jax.random.key(0)).params
        head = params["latent_head"]
        assert head["Dense_0"]["kernel"].shape == (8 + OBS * skip, 6) and head["Dense_1"]["kernel"].shape == (6, 12)
        z = agent.latent_of(params, h, obs)
        np.testing.assert_allclose(np.asarray(z), np_latent_head(head, h, obs if skip else None, 4),
                                   rtol=1e-4, atol=1e-6)
    assert "model.latent_head_hidden" in tiny("cfc-zp-det").config.inactive_fields()
    with pytest.raises(ValueError, match=r"latent_head_hidden=6 needs latent_head='simnorm'"):
        tiny("cfc-zp-det", latent_head_hidden=6)
    with pytest.raises(ValueError, match=r"latent_head_hidden=-1 is invalid; expected an integer >= 0"):
        tiny("cfc-zp-det", latent_head="simnorm", simnorm_dim=4, latent_head_hidden=-1)
