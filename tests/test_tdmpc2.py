"""TD-MPC2 agent: losses against a float64 numpy reference, update mechanics, acting."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lnn_helpers import quick_jit

from lnnmpc.agents import math as M
from lnnmpc.agents.mppi import MPPIConfig
from lnnmpc.agents.tdmpc2 import TDMPC2, TDMPC2Config, clip_jointly, learning_rate
from lnnmpc.agents.tdmpc2_model import WorldModelConfig

H, B, OBS, ACT = 3, 16, 5, 2


@pytest.fixture(scope="module")
def agent():
    model = WorldModelConfig.from_size(OBS, ACT, 1, enc_dim=32, mlp_dim=32, latent_dim=16, num_q=2, q_dropout=0.0)
    planner = MPPIConfig(num_samples=64, num_policy_trajectories=8, num_elites=8, iterations=2)
    return TDMPC2(TDMPC2Config(model=model, planner=planner, horizon=H))


def _batch(seed=0):
    keys = jax.random.split(jax.random.key(seed), 3)
    return {"obs": jax.random.normal(keys[0], (H + 1, B, OBS)),
            "action": jnp.tanh(jax.random.normal(keys[1], (H + 1, B, ACT))),
            "reward": jax.random.uniform(keys[2], (H + 1, B))}


def _np_soft_ce(logits, target, num_bins=101, vmin=-10.0, vmax=10.0):
    """Independent float64 two-hot cross-entropy."""
    logits, target = np.asarray(logits, np.float64), np.asarray(target, np.float64)
    x = np.clip(np.sign(target) * np.log1p(np.abs(target)), vmin, vmax)
    width = (vmax - vmin) / (num_bins - 1)
    pos = (x - vmin) / width
    low = np.clip(np.floor(pos).astype(int), 0, num_bins - 1)
    frac = pos - low
    high = np.clip(low + 1, 0, num_bins - 1)
    probs = np.zeros(logits.shape)
    np.put_along_axis(probs, low[..., None], (1 - frac)[..., None], axis=-1)
    np.put_along_axis(probs, high[..., None], np.take_along_axis(probs, high[..., None], -1) + frac[..., None], -1)
    shifted = logits - logits.max(-1, keepdims=True)
    log_softmax = shifted - np.log(np.exp(shifted).sum(-1, keepdims=True))
    return -(probs * log_softmax).sum(-1)


@pytest.mark.parametrize("target_q", ["min", "mean"])
def test_world_model_loss_matches_numpy_reference(agent, target_q):
    """TD targets bootstrap on the minimum of the two target heads drawn (TD-MPC2) or, ``target_q="mean"``, on
    their mean; with two heads both are drawn, so the reference combines both."""
    agent = type(agent)(dataclasses.replace(agent.config, target_q=target_q))
    state = agent.init(jax.random.key(0))
    # Non-zero reward/Q output layers, so the cross-entropies are not trivially log(101).
    params = jax.tree_util.tree_map(lambda x: x + 0.05 * jnp.sin(jnp.arange(x.size).reshape(x.shape)), state.params)
    batch, key = _batch(), jax.random.key(7)
    total, (_, metrics) = jax.jit(agent.world_model_loss)(params, params["q_heads"], batch, key)

    apply = lambda *a, method, **kw: np.asarray(agent.model.apply({"params": params}, *a, method=method, **kw),
                                                np.float64)
    k_pi, _, _ = jax.random.split(key, 3)
    obs, action, reward = batch["obs"], batch["action"][:-1], np.asarray(batch["reward"][:-1], np.float64)
    next_z = apply(obs[1:], method="encode")
    mean, raw = agent.model.apply({"params": params}, jnp.asarray(next_z, jnp.float32), method="policy")
    next_a = M.sample_tanh_gaussian(k_pi, mean, raw).action
    bins = np.asarray(M.bin_values(), np.float64)
    q_logits = apply(jnp.asarray(next_z, jnp.float32), next_a, method="q")
    probs = np.exp(q_logits - q_logits.max(-1, keepdims=True))
    probs /= probs.sum(-1, keepdims=True)
    sym = probs @ bins
    heads_q = np.sign(sym) * np.expm1(np.abs(sym))
    assert np.abs(heads_q[0] - heads_q[1]).max() > 1e-3  # the heads disagree: min and mean differ
    td = reward + 0.99 * (heads_q.min(axis=0) if target_q == "min" else heads_q.mean(axis=0))
    zs = [apply(obs[0], method="encode")]
    for t in range(H):
        zs.append(apply(jnp.asarray(zs[-1], jnp.float32), action[t], method="next"))
    zs = np.stack(zs)
    w = 0.5 ** np.arange(H)
    consistency = np.sum(w * ((zs[1:] - next_z) ** 2).mean(axis=(1, 2))) / H
    r_logits = apply(jnp.asarray(zs[:-1], jnp.float32), action, method="reward")
    reward_loss = np.sum(w * _np_soft_ce(r_logits, reward).mean(1)) / H
    q_all = apply(jnp.asarray(zs[:-1], jnp.float32), action, method="q")
    value_loss = np.sum(w * _np_soft_ce(q_all, td[None]).mean(2).sum(0)) / (H * 2)
    np.testing.assert_allclose(float(metrics["consistency_loss"]), consistency, rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(float(metrics["reward_loss"]), reward_loss, rtol=1e-4)
    np.testing.assert_allclose(float(metrics["value_loss"]), value_loss, rtol=1e-4)
    np.testing.assert_allclose(float(total), 20 * consistency + 0.1 * reward_loss + 0.1 * value_loss, rtol=1e-4)


def test_updates_learn_a_fixed_batch_and_respect_parameter_groups(agent):
    state = agent.init(jax.random.key(1))
    batch = _batch(1)
    update = jax.jit(agent.update)
    first = None
    for i in range(30):
        new_state, metrics = update(state, batch, jax.random.key(100 + i))
        if i == 0:
            first = metrics
            # Target Q moved by exactly tau towards the online heads.
            expected = M.polyak(state.target_q, new_state.params["q_heads"], 0.01)
            for a, b in zip(jax.tree_util.tree_leaves(expected), jax.tree_util.tree_leaves(new_state.target_q),
                            strict=True):
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-8)
        state = new_state
    assert float(metrics["reward_loss"]) < float(first["reward_loss"]) - 0.1
    assert float(metrics["value_loss"]) < float(first["value_loss"]) - 0.1
    assert all(np.isfinite(float(v)) for v in metrics.values())
    assert int(state.updates) == 30


def test_policy_head_is_only_trained_by_the_policy_loss(agent):
    state = agent.init(jax.random.key(2))
    params = state.params
    grads = jax.tree_util.tree_map(jnp.ones_like, params)
    updates, _ = agent.model_tx.update(grads, state.model_opt, params)
    assert all(float(jnp.abs(x).max()) == 0 for x in jax.tree_util.tree_leaves(updates["policy_head"]))
    assert float(jnp.abs(updates["dynamics"]["Dense_0"]["kernel"]).max()) > 0
    # Encoder steps are 0.3x the others (Adam's first step is lr * sign(grad)).
    step_size = lambda group: jnp.abs(updates[group]["Dense_0"]["kernel"]).max()
    ratio = step_size("encoder") / step_size("dynamics")
    np.testing.assert_allclose(float(ratio), 0.3, rtol=1e-3)
    pi_updates, _ = agent.policy_tx.update(grads, state.policy_opt, params)
    assert float(jnp.abs(pi_updates["policy_head"]["Dense_0"]["kernel"]).max()) > 0
    assert all(float(jnp.abs(x).max()) == 0 for x in jax.tree_util.tree_leaves(pi_updates["encoder"]))


def test_act_under_jit_and_vmap_over_seeds(agent):
    states = jax.vmap(agent.init)(jax.random.split(jax.random.key(3), 3))
    act = jax.jit(jax.vmap(lambda s, o, k: agent.plan(s, o, jnp.zeros((H, ACT)), k, explore=True,
                                                      first_step=jnp.array(True))[:2]))
    obs = jax.random.normal(jax.random.key(4), (3, OBS))
    actions, means = act(states, obs, jax.random.split(jax.random.key(5), 3))
    assert actions.shape == (3, ACT) and means.shape == (3, H, ACT)
    assert np.all(np.abs(np.asarray(actions)) <= 1)
    again, _ = act(states, obs, jax.random.split(jax.random.key(5), 3))
    np.testing.assert_array_equal(np.asarray(actions), np.asarray(again))


def test_config_validation():
    model = WorldModelConfig.from_size(OBS, ACT, 1)
    with pytest.raises(ValueError, match="horizon must be an integer >= 1, got 0"):
        TDMPC2Config(model=model, horizon=0)
    with pytest.raises(ValueError, match=r"gamma must be in \(0, 1\], got 1.5"):
        TDMPC2Config(model=model, gamma=1.5)


def test_world_model_gradient_is_clipped_by_one_global_norm(agent):
    """TD-MPC2 clips all model parameters' gradients together: against float64 numpy on a toy tree, and in the
    update, where Adam's first moment after one step is 0.1 x the gradient the optimiser received."""
    rng = np.random.default_rng(0)
    grads = {k: {"w": rng.normal(size=(3, 4)).astype(np.float32)} for k in ("encoder", "dynamics", "policy_head")}
    clipped = clip_jointly(grads, 1.5, frozen=("policy_head",))
    norm = np.sqrt(sum((grads[k]["w"].astype(np.float64) ** 2).sum() for k in ("encoder", "dynamics")))
    for k in ("encoder", "dynamics"):
        np.testing.assert_allclose(np.asarray(clipped[k]["w"]), grads[k]["w"] * 1.5 / norm, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(clipped["policy_head"]["w"]), grads["policy_head"]["w"])
    small = clip_jointly(grads, 1e3, frozen=("policy_head",))
    np.testing.assert_allclose(np.asarray(small["encoder"]["w"]), grads["encoder"]["w"], rtol=1e-6)

    def first_moment_norm(joint: bool) -> float:
        tight = type(agent)(dataclasses.replace(agent.config, grad_clip_norm=1e-6, joint_grad_clip=joint,
                                                flat_optimizer=False))  # per-leaf state: 'mu' per group
        state, _ = quick_jit(tight.update)(quick_jit(tight.init)(jax.random.key(5)), _batch(5), jax.random.key(6))
        mus = [x for path, x in jax.tree_util.tree_flatten_with_path(state.model_opt)[0]
               if "mu" in jax.tree_util.keystr(path) and "policy_head" not in jax.tree_util.keystr(path)]
        return float(np.sqrt(sum(float(jnp.sum(jnp.square(m))) for m in mus)))

    np.testing.assert_allclose(first_moment_norm(True), 0.1 * 1e-6, rtol=1e-3)  # one norm over both groups
    np.testing.assert_allclose(first_moment_norm(False), 0.1 * 1e-6 * np.sqrt(2), rtol=1e-3)  # each group's own


def test_flat_optimizer_gives_the_per_leaf_optimizers_updates(agent):
    """``flat_optimizer``: one Adam over a flat vector with the groups' learning rates as scales makes the same
    updates as Adam per leaf (the encoder's 0.3 x steps, the frozen groups unmoved), through several updates with
    a binding gradient clip."""
    flat = type(agent)(dataclasses.replace(agent.config, flat_optimizer=True, grad_clip_norm=0.5))
    leafwise = type(agent)(dataclasses.replace(agent.config, flat_optimizer=False, grad_clip_norm=0.5))
    states = [quick_jit(a.init)(jax.random.key(7)) for a in (leafwise, flat)]
    start = states[0].params
    updates = [quick_jit(a.update) for a in (leafwise, flat)]  # XLA's CPU optimisations off: half the compile
    for i in range(4):
        states = [update(state, _batch(10 + i), jax.random.key(20 + i))[0]
                  for update, state in zip(updates, states, strict=True)]
    moved = 0
    for a, b, s in zip(*(jax.tree_util.tree_leaves(st.params) for st in states), jax.tree_util.tree_leaves(start),
                       strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-5, atol=1e-6)
        moved += int(not np.array_equal(np.asarray(a), np.asarray(s)))
    assert moved == len(jax.tree_util.tree_leaves(start))  # every leaf trained, so the comparison is not vacuous
    with pytest.raises(ValueError, match="flat_optimizer=True needs joint_grad_clip=True"):
        dataclasses.replace(agent.config, flat_optimizer=True, joint_grad_clip=False)


@pytest.mark.parametrize("flat", [True, False])
def test_learning_rate_decay_steps_every_group_by_the_schedule(agent, flat):
    """``lr_decay_*``: constant to update 1, linear to 0.1 x at update 3, constant after; Adam's steps on a
    constant gradient are the rate itself, so each update's step is read off against the float64 schedule (the
    encoder's at 0.3 x, the policy head's in the policy optimiser, the frozen groups unmoved)."""
    config = dataclasses.replace(agent.config, flat_optimizer=flat, lr_decay_begin=1, lr_decay_end=3,
                                 lr_final_scale=0.1)
    decayed = TDMPC2(config)
    expected = 3e-4 * np.interp(np.arange(6), [1, 3], [1.0, 0.1])  # [lr, lr, 0.55 lr, 0.1 lr, 0.1 lr, 0.1 lr]
    np.testing.assert_allclose([float(learning_rate(config)(i)) for i in range(6)], expected, rtol=1e-6)
    state = decayed.init(jax.random.key(8))
    params, model_opt, policy_opt = state.params, state.model_opt, state.policy_opt
    grads = jax.tree_util.tree_map(jnp.ones_like, params)
    step = lambda u, group: float(jnp.abs(u[group]["Dense_0"]["kernel"]).max())
    for rate in expected:
        updates, model_opt = decayed.model_tx.update(grads, model_opt, params)
        np.testing.assert_allclose(step(updates, "dynamics"), rate, rtol=1e-4)
        np.testing.assert_allclose(step(updates, "encoder"), 0.3 * rate, rtol=1e-4)
        assert step(updates, "policy_head") == 0.0
        pi_updates, policy_opt = decayed.policy_tx.update(grads, policy_opt, params)
        np.testing.assert_allclose(step(pi_updates, "policy_head"), rate, rtol=1e-3)  # Adam eps 1e-5
        assert step(pi_updates, "dynamics") == 0.0
    if flat:  # the update logs the rate it used (train.csv's lr); without a decay there is no such metric
        _, metrics = quick_jit(decayed.update)(state.replace(updates=jnp.asarray(2)), _batch(2), jax.random.key(9))
        np.testing.assert_allclose(float(metrics["lr"]), expected[2], rtol=1e-6)
        assert callable(learning_rate(config)) and learning_rate(agent.config) == 3e-4


def test_learning_rate_decay_validation_names_the_bad_value():
    model = WorldModelConfig.from_size(OBS, ACT, 1)
    with pytest.raises(ValueError, match=r"lr_final_scale must be in \(0, 1\] .*got 0"):
        TDMPC2Config(model=model, lr_final_scale=0, lr_decay_end=10)
    with pytest.raises(ValueError, match=r"lr_final_scale must be in \(0, 1\] .*got 1.5"):
        TDMPC2Config(model=model, lr_final_scale=1.5)
    with pytest.raises(ValueError, match="lr_decay_end=100 must exceed lr_decay_begin=100 when lr_final_scale=0.1"):
        TDMPC2Config(model=model, lr_final_scale=0.1, lr_decay_begin=100, lr_decay_end=100)
    with pytest.raises(ValueError, match=r"lr_decay_begin must be an integer >= 0 \(an update count\), got -1"):
        TDMPC2Config(model=model, lr_decay_begin=-1)
    constant = TDMPC2Config(model=model, lr_decay_begin=5)  # no decay: the updates are inactive, not compared
    assert constant.inactive_fields() == {"lr_decay_begin", "lr_decay_end"}
    assert TDMPC2Config(model=model, lr_final_scale=0.5, lr_decay_end=10).inactive_fields() == set()
