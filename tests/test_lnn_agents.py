"""LNN-TD-MPC2 agents: configuration and overrides, burn-in isolation, acting encoder, OP planning step."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from lnn_helpers import quick_jit, tiny_agent

from lnnmpc.agents import math as M
from lnnmpc.agents.lnn import LNNTDMPC2
from lnnmpc.agents.overrides import apply_overrides, apply_planner_overrides, planner_keys
from lnnmpc.agents.registry import AGENTS, LNN_AGENTS, make_agent

OBS, ACT, B = 5, 2, 8


def tiny(name: str, **overrides) -> LNNTDMPC2:
    return tiny_agent(name, OBS, ACT, **overrides)


def window(agent: LNNTDMPC2, seed: int = 0) -> dict:
    """A random time-major training window of ``agent.sequence_length`` records."""
    S, N = agent.sequence_length, agent.config.model.hidden_size
    k = jax.random.split(jax.random.key(seed), 6)
    action = jnp.tanh(jax.random.normal(k[1], (S, B, ACT)))
    return {"obs": jax.random.normal(k[0], (S, B, OBS)), "action": action,
            "reward": jax.random.uniform(k[2], (S, B)), "dt": jax.random.randint(k[3], (S, B), 1, 3) * 1.0,
            "h_prev": 0.5 * jnp.tanh(jax.random.normal(k[4], (S, B, N))),
            "prev_action": jnp.concatenate([jnp.zeros((1, B, ACT)), action[:-1]])}


def test_light_configuration_defaults():
    agent = make_agent("cfc-zp-det", OBS, ACT)
    c = agent.config
    assert (c.model.hidden_size, c.model.latent_dim, c.model.mlp_dim, c.model.num_q) == (64, 64, 192, 2)
    assert (c.planner.horizon, c.horizon, c.burn_in, c.lambda_, c.rho) == (10, 32, 10, 0.95, 1.0)
    assert (c.gamma, c.lr, c.encoder_lr_scale, c.grad_clip_norm, c.tau) == (0.99, 3e-4, 0.3, 20.0, 0.01)
    assert agent.sequence_length == 43
    assert set(LNN_AGENTS) == {f"{a}-{b}-{c}" for a in ("cfc", "ltc") for b in ("zp", "op") for c in ("det", "stoch")}
    assert set(LNN_AGENTS) < set(AGENTS) and "tdmpc2" in AGENTS
    ltc = make_agent("ltc-op-stoch", OBS, ACT).config.model
    assert (ltc.cell, ltc.objective, ltc.stochastic, ltc.ode_unfolds) == ("ltc", "op", True, 6)


def test_overrides_are_converted_validated_and_listed():
    agent = make_agent("cfc-op-det", OBS, ACT, overrides={"burn_in": "20", "lambda_": 0.9, "plan_horizon": 5,
                                                           "gamma": "0.95", "cell": "ltc", "stochastic": "true",
                                                           "hidden_size": 32.0})
    c = agent.config
    assert (c.burn_in, c.lambda_, c.planner.horizon, c.horizon) == (20, 0.9, 5, 32)
    assert c.gamma == c.planner.gamma == 0.95  # one gamma for targets and planner
    assert (c.model.cell, c.model.stochastic, c.model.hidden_size) == ("ltc", True, 32)
    assert agent.initial_carry().plan_mean.shape == (5, ACT)
    with pytest.raises(ValueError, match=r"unknown hyperparameter 'latent'; allowed: .*burn_in.*plan_horizon"):
        make_agent("cfc-zp-det", OBS, ACT, overrides={"latent": 3})
    with pytest.raises(ValueError, match=r"burn_in='x' is not a valid int"):
        make_agent("cfc-zp-det", OBS, ACT, overrides={"burn_in": "x"})
    with pytest.raises(ValueError, match=r"burn_in=2.5 is not a valid int"):
        make_agent("cfc-zp-det", OBS, ACT, overrides={"burn_in": 2.5})
    with pytest.raises(ValueError, match=r"lambda_ must be in \[0, 1\], got 1.5"):
        make_agent("cfc-zp-det", OBS, ACT, overrides={"lambda_": 1.5})
    with pytest.raises(ValueError, match=r"cell='gru' is not supported; allowed values: \['cfc', 'ltc'\]"):
        make_agent("cfc-zp-det", OBS, ACT, overrides={"cell": "gru"})
    with pytest.raises(ValueError, match=r"planner: horizon=0 is invalid; .* \(set by plan_horizon=0\)"):
        make_agent("cfc-zp-det", OBS, ACT, overrides={"plan_horizon": 0})
    with pytest.raises(ValueError, match=r"model: .*num_q.* \(set by num_q='1'\)"):
        make_agent("tdmpc2", OBS, ACT, overrides={"num_q": "1", "lr": 1e-3})
    with pytest.raises(ValueError, match="unknown agent 'cfc-xp-det'"):
        make_agent("cfc-xp-det", OBS, ACT)
    tdmpc2 = make_agent("tdmpc2", OBS, ACT, overrides={"plan_horizon": "4", "horizon": 5, "num_q": 3})
    assert (tdmpc2.config.planner.horizon, tdmpc2.config.horizon, tdmpc2.config.model.num_q) == (4, 5, 3)
    dotted = make_agent("tdmpc2", OBS, ACT, overrides={"planner.horizon": 6, "model.num_q": "4", "planner.gamma": 0.9})
    assert (dotted.config.planner.horizon, dotted.config.model.num_q, dotted.config.planner.gamma) == (6, 4, 0.9)
    assert dotted.config.gamma == 0.99  # the section.field spelling sets that one field only
    with pytest.raises(ValueError, match=r"unknown hyperparameter 'planner.lr'"):
        make_agent("tdmpc2", OBS, ACT, overrides={"planner.lr": 1.0})
    with pytest.raises(ValueError, match=r"unknown hyperparameter 'burn_in'"):
        make_agent("tdmpc2", OBS, ACT, overrides={"burn_in": 3})
    decay = make_agent("cfc-op-det", OBS, ACT, overrides={"lr_decay_begin": "50000", "lr_decay_end": 1e5,
                                                         "lr_final_scale": "0.1"}).config
    assert (decay.lr_decay_begin, decay.lr_decay_end, decay.lr_final_scale) == (50_000, 100_000, 0.1)
    assert not {"lr_decay_begin", "lr_decay_end"} & decay.inactive_fields()  # compared on resume
    plain = make_agent("cfc-op-det", OBS, ACT).config
    assert {"lr_decay_begin", "lr_decay_end", "free_bits"} <= plain.inactive_fields()


def test_planner_overrides_change_the_planner_and_refuse_anything_else():
    """What ``eval --planner`` may change: only planner fields (the trained parameters do not depend on them)."""
    config = make_agent("cfc-op-det", OBS, ACT).config
    assert planner_keys(config) == ["explore_min_std", "iterations", "max_std", "min_std", "num_elites",
                                    "num_policy_trajectories", "num_samples", "plan_horizon", "temperature",
                                    "terminal_q", "unroll"]
    changed = apply_planner_overrides(config, {"iterations": "12", "plan_horizon": 5, "planner.gamma": 0.9})
    assert (changed.planner.iterations, changed.planner.horizon, changed.planner.gamma) == (12, 5, 0.9)
    assert changed.gamma == 0.99 and changed.model == config.model and changed.horizon == config.horizon
    assert apply_planner_overrides(config, {}) is config
    with pytest.raises(ValueError, match=r"'gamma', 'num_q' is not a planner setting; an evaluation may change "
                                         r"only: explore_min_std, .*terminal_q, unroll \(or planner.FIELD\)"):
        apply_planner_overrides(config, {"num_q": 5, "gamma": 0.9, "iterations": 2})
    with pytest.raises(ValueError, match=r"planner: .*num_elites.* \(set by num_elites=1000\)"):
        apply_planner_overrides(config, {"num_elites": 1000})
    from lnnmpc.train.config import ConfigError
    from lnnmpc.train.evaluate import with_planner

    agent = make_agent("cfc-op-det", OBS, ACT)
    rebuilt = with_planner(agent, {"plan_horizon": 5})
    assert type(rebuilt) is LNNTDMPC2 and rebuilt.config == dataclasses.replace(
        agent.config, planner=dataclasses.replace(agent.config.planner, horizon=5))
    assert rebuilt.initial_carry().plan_mean.shape == (5, ACT) and with_planner(agent, None) is agent
    with pytest.raises(ConfigError, match="'lr' is not a planner setting"):
        with_planner(agent, {"lr": 1e-3})


def test_evaluations_of_equal_agents_and_environments_share_one_program():
    """``mjx_evaluator``'s compiled program is kept per (agent class and configuration, environment, sizes):
    a rebuilt agent of the same configuration reuses it, other planner settings, the prior acting, other
    corruptions or sizes get their own (nothing is traced or compiled here: jit is lazy)."""
    from lnnmpc import envs
    from lnnmpc.agents.actor import with_actor
    from lnnmpc.train.evaluate import SameProgram, _evaluation_program, with_planner

    def program(agent, env, episodes, seeds):
        return _evaluation_program(SameProgram(agent, env), episodes, seeds)

    env = envs.make("cartpole-swingup")
    agent = make_agent("cfc-op-det", env.observation_size, env.action_size)
    first = program(agent, env, 2, 1)
    assert program(type(agent)(agent.config), envs.make("cartpole-swingup"), 2, 1) is first
    others = [program(with_planner(agent, {"plan_horizon": 5}), env, 2, 1),
              program(with_actor(agent, "prior"), env, 2, 1),
              program(agent, envs.make("cartpole-swingup", obs_noise=0.1), 2, 1),
              program(agent, envs.make("cartpole-swingup", physics="exact"), 2, 1),
              program(agent, env, 3, 1), program(agent, env, 2, 2)]
    assert len({id(p) for p in [first, *others]}) == 7
    assert program(with_actor(agent, "prior"), env, 2, 1) is others[1]


@pytest.fixture(scope="module")
def zp_agent():
    agent = tiny("cfc-zp-det")
    return agent, quick_jit(agent.init)(jax.random.key(0))


def test_burn_in_gets_no_gradient(zp_agent):
    agent, state = zp_agent
    batch, key, T = window(agent), jax.random.key(1), agent.config.burn_in

    def loss_of(params, batch):
        return agent.world_model_loss(params, state.target_q, batch, key)[0]

    grad_params, grad_batch = quick_jit(jax.grad(loss_of, argnums=(0, 1)))(state.params, batch)
    # Nothing before the learning steps gets a gradient: the burn-in inputs and the stored start state.
    for name in ("obs", "prev_action", "dt"):
        assert float(jnp.abs(grad_batch[name][:T]).max()) == 0.0, name
        assert float(jnp.abs(grad_batch[name][T:]).max()) > 0.0, name
    assert float(jnp.abs(grad_batch["h_prev"]).max()) == 0.0
    # The parameter gradient equals that of a window starting at the burned-in state with no burn-in at all.
    h_T = agent.encode_sequence(state.params, batch["h_prev"][0], batch["obs"][:T], batch["prev_action"][:T],
                                batch["dt"][:T])[-1]
    no_burn_in = LNNTDMPC2(dataclasses.replace(agent.config, burn_in=0))
    rest = {k: v[T:] for k, v in batch.items()}
    rest["h_prev"] = rest["h_prev"].at[0].set(h_T)
    expected = quick_jit(jax.grad(lambda p: no_burn_in.world_model_loss(p, state.target_q, rest, key)[0]))(
        state.params)
    for got, want in zip(jax.tree_util.tree_leaves(grad_params), jax.tree_util.tree_leaves(expected), strict=True):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-4, atol=1e-6)
    # ... while the burn-in does set the starting state (the loss depends on it).
    other = {**batch, "obs": batch["obs"].at[:T].add(1.0)}
    loss = quick_jit(loss_of)
    assert abs(float(loss(state.params, other)) - float(loss(state.params, batch))) > 1e-4


def test_act_encodes_like_the_training_unroll(zp_agent):
    """The actor's per-step encoder state equals the training-time unroll over the same history."""
    agent, state = zp_agent
    batch = window(agent, seed=3)
    act = quick_jit(lambda c, o, dt, k, f: agent.act(state, c, o, dt, k, explore=True, first_step=f))
    carry, actions, hs = agent.initial_carry(), [], []
    for t in range(5):
        assert np.allclose(carry.prev_action, actions[-1] if actions else 0.0)
        action, carry = act(carry, batch["obs"][t, 0], batch["dt"][t, 0], jax.random.key(t), jnp.array(t == 0))
        actions.append(action)
        hs.append(carry.h)
    obs, dt = batch["obs"][:5, :1], batch["dt"][:5, :1]
    prev = jnp.stack([jnp.zeros(ACT)] + actions[:-1])[:, None]
    states = agent.encode_sequence(state.params, jnp.zeros((1, agent.config.model.hidden_size)), obs, prev, dt)
    np.testing.assert_allclose(np.stack(hs), np.asarray(states[:, 0]), rtol=1e-5, atol=1e-5)
    # observe (seed phase: someone else's action) advances the encoder like act and keeps that action.
    observe = quick_jit(lambda c, o, dt, a, f: agent.observe(state, c, o, dt, a, first_step=f))
    seen = observe(carry, batch["obs"][5, 0], batch["dt"][5, 0], jnp.array([0.25, -0.5]), jnp.array(False))
    _, acted = act(carry, batch["obs"][5, 0], batch["dt"][5, 0], jax.random.key(5), jnp.array(False))
    np.testing.assert_allclose(np.asarray(seen.h), np.asarray(acted.h), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(seen.prev_action), [0.25, -0.5])
    np.testing.assert_array_equal(np.asarray(seen.plan_mean), np.asarray(carry.plan_mean))
    # A first step ignores the carry it is given.
    again, fresh = act(carry, batch["obs"][0, 0], batch["dt"][0, 0], jax.random.key(0), jnp.array(True))
    np.testing.assert_allclose(np.asarray(fresh.h), np.asarray(hs[0]), rtol=1e-6)


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


@pytest.mark.parametrize("name", ["cfc-op-det", "ltc-op-stoch"])
def test_op_planning_step_is_the_encoder_on_the_prediction(name):
    agent = tiny(name)
    state = quick_jit(agent.init)(jax.random.key(4))
    params, N = state.params, agent.config.model.hidden_size
    z, a = 0.5 * jnp.tanh(jax.random.normal(jax.random.key(5), (N,))), jnp.array([0.3, -0.7])
    key = jax.random.key_data(jax.random.key(6))
    model = agent.planning_model(params)
    stepped = quick_jit(model.dynamics)({"z": z, "key": key}, a)

    apply = lambda *args, method: agent.model.apply({"params": params}, *args, method=method)
    mean, sigma = apply(z, a, method="predict")
    k_noise, k_next = jax.random.split(jax.random.wrap_key_data(key))
    predicted_obs = mean if sigma is None else mean + sigma * jax.random.normal(k_noise, mean.shape)
    assert predicted_obs.shape == (OBS,)
    expected = apply(z[None], predicted_obs[None], a[None], jnp.ones((1,)), method="encode_step")[0]
    np.testing.assert_allclose(np.asarray(stepped["z"]), np.asarray(expected), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(stepped["key"]), np.asarray(jax.random.key_data(k_next)))
    if sigma is not None:  # the stochastic transition samples: another key gives another next latent
        other = model.dynamics({"z": z, "key": jax.random.key_data(jax.random.key(7))}, a)
        assert float(jnp.abs(other["z"] - stepped["z"]).max()) > 1e-4


@pytest.mark.parametrize("name", ["cfc-zp-det", "tdmpc2"])
def test_planning_value_is_the_mean_or_the_min_of_the_two_heads_drawn(name):
    """``terminal_q`` (``--set terminal_q=min``, ``eval --planner terminal_q=min``): the planner's terminal value is
    the mean of the two Q heads drawn with the value's key (TD-MPC2) or their minimum; the heads are made to
    disagree (their parameters perturbed apart) so that mean and min differ."""
    agent = tiny(name) if name != "tdmpc2" else make_agent("tdmpc2", OBS, ACT, small=True)
    state = quick_jit(agent.init)(jax.random.key(4))
    noise = jax.tree.map(lambda x: 0.3 * jax.random.normal(jax.random.key(8), x.shape, x.dtype),
                         state.params["q_heads"])
    params = {**state.params, "q_heads": jax.tree.map(jnp.add, state.params["q_heads"], noise)}
    z = 0.5 * jnp.tanh(jax.random.normal(jax.random.key(5), (agent.config.model.latent_dim if name == "tdmpc2"
                                                            else agent.config.model.hidden_size,)))
    a, key = jnp.array([0.3, -0.7]), jax.random.key(6)
    latent = z if name == "tdmpc2" else {"z": z, "key": jax.random.key_data(jax.random.key(7))}
    heads = np.asarray(agent._q_values(params, z, a, agent._two_heads(key)))
    assert heads.shape == (2,) and abs(heads[0] - heads[1]) > 1e-3
    values = {}
    for how in ("mean", "min"):
        config = dataclasses.replace(agent.config, planner=dataclasses.replace(agent.config.planner, terminal_q=how))
        values[how] = float(type(agent)(config).planning_model(params).value(latent, a, key))
    np.testing.assert_allclose(values["mean"], heads.mean(), rtol=1e-6)
    np.testing.assert_allclose(values["min"], heads.min(), rtol=1e-6)
    with pytest.raises(ValueError, match=r"terminal_q='max' is invalid; expected one of mean, min"):
        apply_planner_overrides(agent.config, {"terminal_q": "max"})


def test_target_q_combines_the_target_heads_by_their_minimum_or_mean_and_is_validated(zp_agent):
    """``--set target_q=mean``: the TD targets bootstrap on the mean of the two target heads drawn instead of their
    minimum (TD-MPC2's); with heads that disagree the value loss moves, and nothing else of the loss does."""
    agent, state = zp_agent
    heads = jnp.array([[1.0, -2.0, 4.0], [3.0, 0.0, 4.0]])
    mean_agent = type(agent)(dataclasses.replace(agent.config, target_q="mean"))
    np.testing.assert_array_equal(np.asarray(agent._target_value(heads)), [1.0, -2.0, 4.0])
    np.testing.assert_array_equal(np.asarray(mean_agent._target_value(heads)), [2.0, -1.0, 4.0])
    noise = jax.tree.map(lambda x: 0.3 * jax.random.normal(jax.random.key(8), x.shape, x.dtype),
                         state.params["q_heads"])
    params = {**state.params, "q_heads": jax.tree.map(jnp.add, state.params["q_heads"], noise)}
    batch, key = window(agent), jax.random.key(3)
    losses = {how: quick_jit(a.world_model_loss)(params, params["q_heads"], batch, key)[1][1]
              for how, a in (("min", agent), ("mean", mean_agent))}
    assert abs(float(losses["min"]["value_loss"]) - float(losses["mean"]["value_loss"])) > 1e-4
    for name in ("prediction_loss", "reward_loss"):
        np.testing.assert_allclose(float(losses["min"][name]), float(losses["mean"][name]), rtol=1e-6)
    with pytest.raises(ValueError, match=r"target_q='max' is invalid; expected one of mean, min"):
        apply_overrides(agent.config, {"target_q": "max"})
    assert apply_overrides(agent.config, {"target_q": "mean"}).target_q == "mean"


def test_symlog_input_transform_squashes_what_the_cell_reads(zp_agent):
    """input_transform="symlog": acting and the training unroll both feed the cell sign(o)·log(1+|o|)."""
    agent, state = zp_agent
    squashing = LNNTDMPC2(dataclasses.replace(
        agent.config, model=dataclasses.replace(agent.config.model, input_transform="symlog")))
    batch = window(agent, seed=9)
    obs = 20.0 * batch["obs"][:4, :2]  # walker-sized inputs
    prev, dt, h0 = batch["prev_action"][:4, :2], batch["dt"][:4, :2], batch["h_prev"][0, :2]
    squashed_np = np.sign(np.asarray(obs, np.float64)) * np.log1p(np.abs(np.asarray(obs, np.float64)))
    got = squashing.encode_sequence(state.params, h0, obs, prev, dt)
    want = agent.encode_sequence(state.params, h0, jnp.asarray(squashed_np, jnp.float32), prev, dt)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-6)
    assert float(jnp.abs(got - agent.encode_sequence(state.params, h0, obs, prev, dt)).max()) > 1e-3
    one = squashing.model.apply({"params": state.params}, h0, obs[0], prev[0], dt[0], method="encode_step")
    np.testing.assert_allclose(np.asarray(one), np.asarray(got[0]), rtol=1e-5, atol=1e-6)
    allowed = r"input_transform='log' is not supported; allowed values: \['none', 'symlog'\]"
    with pytest.raises(ValueError, match=allowed):
        make_agent("cfc-zp-det", OBS, ACT, overrides={"input_transform": "log"})
    assert make_agent("ltc-op-det", OBS, ACT, overrides={"input_transform": "symlog"}).config.model.input_transform \
        == "symlog"


@pytest.mark.parametrize("name", ["cfc-zp-stoch", "cfc-op-stoch"])
def test_stochastic_prediction_loss_is_the_beta_nll_of_the_predictor(name):
    """The stochastic variants' per-step loss and diagnostics from the predictor's (mean, σ), against float64
    numpy, for the default β = 1 and the thesis's plain NLL (β = 0); free bits only for OP."""
    assert (make_agent(name, OBS, ACT).config.nll_beta, make_agent(name, OBS, ACT).config.free_bits) == (1.0, -2.0)
    with pytest.raises(ValueError, match=r"nll_beta must be in \[0, 1\], got 2.0"):
        make_agent(name, OBS, ACT, overrides={"nll_beta": 2})
    op = name.split("-")[1] == "op"
    for beta in (1.0, 0.0):
        agent = tiny(name, nll_beta=beta, free_bits=0.7)  # untrained σ ≈ softplus(0): exact NLL ≈ 0.55
        state = agent.init(jax.random.key(0))
        k = jax.random.split(jax.random.key(4), 3)
        H, D = 3, agent.config.model.target_dim
        z = jax.random.normal(k[0], (H, B, agent.config.model.hidden_size))
        action = jnp.tanh(jax.random.normal(k[1], (H, B, ACT)))
        close = agent._apply(state.params, z, action, method="predict")[0] + 0.01 * jax.random.normal(k[2], (H, B, D))
        target = jnp.where(jnp.arange(B)[:, None] < B // 2, close, 2.0 * jax.random.normal(k[2], (H, B, D)))
        loss, info = agent.prediction_loss(state.params, z, action, target)
        mean, sigma = (np.asarray(x, np.float64) for x in agent._apply(state.params, z, action, method="predict"))
        per_dim = 0.5 * ((np.asarray(target) - mean) / sigma) ** 2 + np.log(sigma) + 0.5 * np.log(2 * np.pi)
        nll = per_dim.mean(-1)
        weighted = (sigma ** (2 * beta) * per_dim).mean(-1)
        if op:
            floored = nll <= 0.7
            assert floored.any() and not floored.all()  # the test exercises both branches
            weighted = np.where(floored, np.maximum(weighted, 0.7) if beta == 0 else weighted, weighted)
            nll = np.maximum(nll, 0.7)
            np.testing.assert_allclose(info["free_bits_floored"], floored.mean(1), rtol=1e-6)
        else:
            assert "free_bits_floored" not in info
        np.testing.assert_allclose(loss, weighted.mean(1), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(info["prediction_nll"], nll.mean(1), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(info["prediction_sigma"], sigma.mean((1, 2)), rtol=1e-5)


@pytest.mark.parametrize("name", ["cfc-zp-det", "cfc-op-det"])
def test_rollout_losses_are_taken_on_the_planners_own_latents(name):
    """``rollout_steps`` K = 2: each loss is the mean of depth 0 (the thesis's, on the encoder's latents) and
    depth 1, the planner's transition T(z_{t-1}, a_{t-1}) at positions 1..H-1, built here by hand from the
    model's pieces (no dropout: the tiny agents have none)."""
    one, two = tiny(name), tiny(name, rollout_steps=2)
    state = quick_jit(one.init)(jax.random.key(3))
    batch, key, T, H = window(one, seed=4), jax.random.key(5), one.config.burn_in, one.config.horizon
    loss_one, (_, m1) = quick_jit(one.world_model_loss)(state.params, state.target_q, batch, key)
    loss_two, (_, m2) = quick_jit(two.world_model_loss)(state.params, state.target_q, batch, key)

    def by_hand(params):
        cfg, bins = one.config, one.config.model.num_bins
        apply = lambda *args, **kw: one.model.apply({"params": params}, *args, **kw)
        zs = one.latents(params, batch)
        action, reward = batch["action"][T:T + H], batch["reward"][T:T + H]
        target = zs[1:] if cfg.model.objective == "zp" else batch["obs"][T + 1:]
        z1 = apply(zs[:H - 1], action[:H - 1], method="transition")  # depth 1 at positions 1..H-1
        pred = apply(z1, action[1:], method="predict")[0]
        reward_ce = M.soft_cross_entropy(apply(z1, action[1:], method="reward"), reward[1:], bins, cfg.vmin,
                                         cfg.vmax)
        return jnp.mean((pred - target[1:]) ** 2), jnp.mean(reward_ce)

    pred1, reward1 = quick_jit(by_hand)(state.params)
    np.testing.assert_allclose(float(m2["rollout_prediction_loss"]), float(pred1), rtol=1e-5)
    np.testing.assert_allclose(float(m2["prediction_loss"]), (float(m1["prediction_loss"]) + float(pred1)) / 2,
                               rtol=1e-5)
    np.testing.assert_allclose(float(m2["reward_loss"]), (float(m1["reward_loss"]) + float(reward1)) / 2, rtol=1e-5)
    assert "rollout_prediction_loss" not in m1 and float(loss_two) != float(loss_one)
    # The depth-1 losses reach the predictor through the transition that made z1 (gradients through the rollout).
    only_depth1 = lambda p: two.world_model_loss(p, state.target_q, batch, key)[1][1]["rollout_prediction_loss"]
    grads = quick_jit(jax.grad(only_depth1))(state.params)
    assert float(optax.tree.norm(grads["predictor"])) > 0 and float(optax.tree.norm(grads["encoder"])) > 0


@pytest.mark.parametrize("name", ["cfc-zp-det", "ltc-op-det"])
def test_three_depths_are_split_back_at_their_own_positions(name):
    """``rollout_steps`` K = 3 stacks the depths' latents (H, H - 1, H - 2 positions) for one pass of the heads:
    the deepest depth's prediction loss is that of the transition applied twice, at positions 2..H-1, by hand."""
    agent = tiny(name, rollout_steps=3)
    state = quick_jit(agent.init)(jax.random.key(9))
    batch, key, T, H = window(agent, seed=10), jax.random.key(11), agent.config.burn_in, agent.config.horizon
    _, (_, metrics) = quick_jit(agent.world_model_loss)(state.params, state.target_q, batch, key)

    def depth_two(params):
        apply = lambda *args, **kw: agent.model.apply({"params": params}, *args, **kw)
        zs, action = agent.latents(params, batch), batch["action"][T:T + H]
        target = zs[1:] if agent.config.model.objective == "zp" else batch["obs"][T + 1:]
        z1 = apply(zs[:H - 1], action[:H - 1], method="transition")  # depth 1 at positions 1..H-1
        z2 = apply(z1[:-1], action[1:H - 1], method="transition")  # depth 2 at positions 2..H-1
        return jnp.mean((apply(z2, action[2:], method="predict")[0] - target[2:]) ** 2)

    np.testing.assert_allclose(float(metrics["rollout_prediction_loss"]), float(quick_jit(depth_two)(state.params)),
                               rtol=1e-5)


@pytest.mark.parametrize("name", ["cfc-zp-det", "cfc-op-det"])
def test_rollout_stride_starts_the_deeper_depths_every_few_positions(name):
    """``rollout_stride`` S = 2 with K = 3 and H = 4: depth 1 starts at positions 0 and 2 (so sits at 1 and 3),
    depth 2 at position 0 only (sits at 2); depth 0 keeps all four positions. Built by hand from the model's
    pieces; with rho != 1 the depth-1 positions are weighted 1 and rho^2."""
    agent = tiny(name, rollout_steps=3, rollout_stride=2, rho=0.5)
    plain = tiny(name, rollout_steps=3, rho=0.5)
    state = quick_jit(agent.init)(jax.random.key(21))
    batch, key, T, H = window(agent, seed=22), jax.random.key(23), agent.config.burn_in, agent.config.horizon
    assert H == 4
    _, (_, metrics) = quick_jit(agent.world_model_loss)(state.params, state.target_q, batch, key)
    _, (_, every) = quick_jit(plain.world_model_loss)(state.params, state.target_q, batch, key)

    def by_hand(params):
        apply = lambda *args, **kw: agent.model.apply({"params": params}, *args, **kw)
        zs, action = agent.latents(params, batch), batch["action"][T:T + H]
        target = zs[1:] if agent.config.model.objective == "zp" else batch["obs"][T + 1:]
        error = lambda z, t: jnp.mean((apply(z, action[t], method="predict")[0] - target[t]) ** 2, axis=(-2, -1))
        depth0 = jnp.sum(0.5 ** jnp.arange(4.0) * error(zs[:4], jnp.arange(4))) / 4
        z1 = apply(zs[jnp.array([0, 2])], action[jnp.array([0, 2])], method="transition")  # at positions 1, 3
        depth1 = jnp.sum(jnp.array([1.0, 0.25]) * error(z1, jnp.array([1, 3]))) / 2
        z2 = apply(z1[:1], action[1:2], method="transition")  # at position 2
        depth2 = error(z2, jnp.array([2]))[0]
        return depth0, depth1, depth2

    depth0, depth1, depth2 = (float(x) for x in quick_jit(by_hand)(state.params))
    np.testing.assert_allclose(float(metrics["rollout_prediction_loss"]), depth2, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["prediction_loss"]), (depth0 + depth1 + depth2) / 3, rtol=1e-5)
    # with S = 1 depth 2 also starts at position 1 (sits at 3), so its loss is another one
    assert abs(float(every["rollout_prediction_loss"]) - depth2) > 1e-4


def test_rollout_stride_is_validated_and_inactive_without_rollouts():
    with pytest.raises(ValueError, match="rollout_stride=0 is invalid; expected an integer >= 1"):
        tiny("cfc-zp-det", rollout_stride=0)
    with pytest.raises(ValueError, match=r"rollout_stride \(5\) must be <= horizon \(4\)"):
        tiny("cfc-zp-det", rollout_stride=5)
    assert "rollout_stride" in tiny("cfc-zp-det").config.inactive_fields()
    assert "rollout_stride" not in tiny("cfc-zp-det", rollout_steps=2).config.inactive_fields()


def test_rollout_steps_are_validated():
    with pytest.raises(ValueError, match="rollout_steps=0 is invalid; expected an integer >= 1"):
        tiny("cfc-zp-det", rollout_steps=0)
    with pytest.raises(ValueError, match=r"rollout_steps \(5\) must be <= horizon \(4\)"):
        tiny("cfc-zp-det", rollout_steps=5)


@pytest.mark.parametrize("name", ["cfc-zp-det", "ltc-op-det"])
def test_scan_unroll_changes_speed_only(name):
    """``scan_unroll`` (encoder steps per scan iteration; >= the window: no loop at all) gives the world-model
    loss and its parameter gradients of the rolled scan (the fused CfC path and the LTC path)."""
    rolled = tiny(name)
    state = quick_jit(rolled.init)(jax.random.key(6))
    batch, key = window(rolled, seed=7), jax.random.key(8)
    loss_of = lambda agent: lambda p: agent.world_model_loss(p, state.target_q, batch, key)[0]
    value = lambda agent: quick_jit(jax.value_and_grad(loss_of(agent)))(state.params)
    jaxpr = lambda agent: str(jax.make_jaxpr(loss_of(agent))(state.params))
    loss, grads = value(rolled)
    for steps in (3, rolled.sequence_length):
        unrolled = tiny(name, scan_unroll=steps)
        assert f"unroll={steps}" in jaxpr(unrolled) and f"unroll={steps}" not in jaxpr(rolled)  # it reached the scan
        got_loss, got_grads = value(unrolled)
        np.testing.assert_allclose(float(got_loss), float(loss), rtol=1e-5)
        for got, want in zip(jax.tree_util.tree_leaves(got_grads), jax.tree_util.tree_leaves(grads), strict=True):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="scan_unroll=0 is invalid; expected an integer >= 1"):
        tiny(name, scan_unroll=0)


@pytest.mark.parametrize("name", ["cfc-zp-det", "ltc-zp-det"])
def test_learn_episode_starts_restarts_the_burn_in_at_the_episode_start(name):
    """With ``learn_episode_starts`` a window may begin up to T records before its episode (``sequence_lead``):
    the encoder restarts from the stored state at the ``first`` record, so the latents equal a fresh unroll from
    that record and nothing before it matters; without the option the same records do change them."""
    agent = tiny(name, learn_episode_starts=True)
    plain = tiny(name)
    T, N = agent.config.burn_in, agent.config.model.hidden_size
    assert (agent.sequence_lead, plain.sequence_lead, agent.sequence_length) == (T, 0, plain.sequence_length)
    assert "learn_episode_starts" in tiny("cfc-zp-det", burn_in=0).config.inactive_fields()
    state = quick_jit(agent.init)(jax.random.key(2))
    starts = np.arange(B) % (T + 1)  # sample b's episode starts at position starts[b], 0..T
    batch = window(agent, seed=4)
    first = jnp.asarray(np.arange(agent.sequence_length)[:, None] == starts[None, :])
    at_start = first[..., None]
    batch = {**batch, "first": first, "h_prev": jnp.where(at_start, 0.0, batch["h_prev"]),  # the stored reset
             "prev_action": jnp.where(at_start, 0.0, batch["prev_action"])}
    before = jnp.asarray(np.arange(agent.sequence_length)[:, None] < starts[None, :])[..., None]
    junk = {**batch, "obs": jnp.where(before, batch["obs"] + 3.0, batch["obs"]),  # the previous episode's end
            "h_prev": batch["h_prev"].at[0].add(jnp.where(starts[:, None] > 0, 0.7, 0.0))}
    latents = quick_jit(agent.latents)
    z = np.asarray(latents(state.params, batch))
    np.testing.assert_array_equal(z, np.asarray(latents(state.params, junk)))
    for b in range(B):  # a fresh unroll from zeros at the episode's first record
        p = int(starts[b])
        one = {k: v[p:, b:b + 1] for k, v in batch.items() if k != "first"}
        states = agent.encode_sequence(state.params, jnp.zeros((1, N)), one["obs"], one["prev_action"], one["dt"])
        np.testing.assert_allclose(z[:, b], np.asarray(states[T - p:, 0]), rtol=1e-5, atol=1e-6)
    plain_latents = quick_jit(plain.latents)
    assert not np.allclose(np.asarray(plain_latents(state.params, batch)),
                           np.asarray(plain_latents(state.params, junk)))
