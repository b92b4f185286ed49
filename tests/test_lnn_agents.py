"""LNN-TD-MPC2 agents: configuration and overrides, burn-in isolation, acting encoder, OP planning step, the
planning value and TD targets' head combinations, input transform."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lnn_helpers import ACT, OBS, quick_jit, tiny, window

from lnnmpc.agents.lnn import LNNTDMPC2
from lnnmpc.agents.overrides import apply_overrides, apply_planner_overrides, planner_keys
from lnnmpc.agents.registry import AGENTS, LNN_AGENTS, make_agent


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
