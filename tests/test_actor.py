"""Acting with the policy prior alone (``lnnmpc.agents.actor``): the action is tanh of the prior's mean at the very
latent MPPI plans from, the encoder reads the step exactly as the planner's act does, and bad names are refused."""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lnn_helpers import perturbed_state

from lnnmpc.agents.actor import ACTORS, PriorActing, with_actor
from lnnmpc.agents.registry import acting_latent, make_agent

OBS_DIM, ACT_DIM = 5, 2


def _prior_mean_action(agent, params, z):
    mean, _ = agent.model.apply({"params": params}, z, method="policy")
    return np.tanh(np.asarray(mean, np.float64))


@pytest.mark.parametrize("name", ["tdmpc2", "cfc-zp-det", "ltc-op-stoch"])
def test_prior_acts_with_tanh_of_its_mean_at_the_planners_latent(name):
    agent = make_agent(name, OBS_DIM, ACT_DIM, small=True)
    state = perturbed_state(agent, jax.random.key(0))
    obs = jax.random.normal(jax.random.key(2), (3, OBS_DIM))
    prior = with_actor(agent, "prior")
    carry = agent.initial_carry()
    for t in range(3):  # a few steps, so an LNN agent's carry matters
        first = jnp.asarray(t == 0)
        planned, after_plan = agent.act(state, carry, obs[t], jnp.asarray(1.0), jax.random.key(10 + t),
                                        explore=False, first_step=first)
        action, after_prior = prior.act(state, carry, obs[t], jnp.asarray(1.0), jax.random.key(20 + t),
                                        explore=False, first_step=first)
        z = acting_latent(agent, state, after_plan, obs[t])
        np.testing.assert_allclose(action, _prior_mean_action(agent, state.params, z), rtol=1e-5, atol=1e-6)
        assert not np.allclose(action, planned, atol=1e-3), "the prior's action is MPPI's"
        again, _ = prior.act(state, carry, obs[t], jnp.asarray(1.0), jax.random.key(99), explore=False,
                             first_step=first)
        np.testing.assert_array_equal(again, action)  # deterministic: the key plays no part
        if hasattr(after_plan, "h"):  # the encoder read the step as the planner's act did; a_{t-1} is the prior's
            np.testing.assert_array_equal(after_prior.h, after_plan.h)
            np.testing.assert_array_equal(after_prior.prev_action, action)
            np.testing.assert_array_equal(after_prior.plan_mean, agent._start(carry, first).plan_mean)
            carry = after_prior
        else:  # TD-MPC2: the warm start passes through
            np.testing.assert_array_equal(after_prior, carry)


def test_exploring_prior_samples_in_bounds_and_by_its_key():
    agent = make_agent("tdmpc2", OBS_DIM, ACT_DIM, small=True)
    state = perturbed_state(agent, jax.random.key(0))
    obs, carry, first = jnp.ones((OBS_DIM,)), agent.initial_carry(), jnp.asarray(True)
    prior = with_actor(agent, "prior")
    a = [prior.act(state, carry, obs, jnp.asarray(1.0), jax.random.key(k), explore=True, first_step=first)[0]
         for k in (0, 0, 1)]
    np.testing.assert_array_equal(a[0], a[1])
    assert not np.allclose(a[0], a[2]) and np.all(np.abs(np.asarray(a)) <= 1.0)  # tanh: float32 may round to 1


def test_actor_names_and_wrapping():
    agent = make_agent("tdmpc2", OBS_DIM, ACT_DIM, small=True)
    assert ACTORS == ("planner", "prior")
    assert with_actor(agent, "planner") is agent
    prior = with_actor(agent, "prior")
    assert isinstance(prior, PriorActing) and prior.config is agent.config  # everything but act is the agent's
    assert copy.copy(prior).agent is agent  # copy builds it without __init__: no recursion through __getattr__
    with pytest.raises(ValueError, match=r"unknown actor 'mpc'; known: planner, prior"):
        with_actor(agent, "mpc")
    with pytest.raises(ValueError, match="has no policy prior"):
        PriorActing(object())
