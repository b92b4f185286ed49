"""LNN-TD-MPC2's model losses over a training window: the stochastic predictors' β-NLL, the open-loop rollout
losses and their depths and stride, the scan's unroll, and the burn-in restarted at episode starts."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from lnn_helpers import ACT, OBS, B, quick_jit, tiny, window

from lnnmpc.agents import math as M
from lnnmpc.agents.registry import make_agent


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
