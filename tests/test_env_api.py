"""Environment API: task list, shapes, time limit, and clear errors for bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lnnmpc import envs

EXPECTED_TASKS = {
    "cartpole-balance", "cartpole-balance-sparse", "cartpole-swingup", "cartpole-swingup-sparse",
    "acrobot-swingup", "acrobot-swingup-sparse", "walker-stand", "walker-walk", "walker-run",
}


def test_all_nine_tasks_with_dm_control_sizes():
    assert set(envs.TASKS) == EXPECTED_TASKS
    sizes = {"cartpole": (5, 1), "acrobot": (6, 1), "walker": (24, 6)}
    for task in EXPECTED_TASKS:
        env = envs.make(task)
        assert (env.observation_size, env.action_size) == sizes[env.spec.domain], task
        assert env.episode_length == 500


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"task": "cartpole-swing"}, "unknown task 'cartpole-swing'.*cartpole-swingup"),
        ({"task": "walker-run", "physics": "turbo"}, "unknown physics profile 'turbo'.*exact, fast"),
        ({"task": "walker-run", "obs_noize": 0.1}, r"unknown observation option.*obs_noize.*obs_noise"),
        ({"task": "walker-run", "obs_noise": -0.1}, "obs_noise must be >= 0.*-0.1"),
        ({"task": "walker-run", "flicker": -1.0}, "flicker must be >= 0.*-1.0"),
        ({"task": "walker-run", "delay": -2}, "delay must be an integer.*>= 0.*-2"),
        ({"task": "walker-run", "delay": 1.5}, "delay must be an integer.*1.5"),
        ({"task": "walker-run", "remove_vel": "yes"}, "remove_vel must be True or False.*yes"),
        ({"task": "walker-run", "action_repeat": 0}, "action_repeat must be an integer >= 1, got 0"),
    ],
)
def test_bad_input_names_value_and_allowed(kwargs, match):
    with pytest.raises(ValueError, match=match):
        kwargs = dict(kwargs)
        task = kwargs.pop("task")
        envs.make(task, **kwargs)


def test_physics_options_validation():
    with pytest.raises(ValueError, match="iterations must be an int >= 1 or None, got 0"):
        envs.PhysicsOptions(iterations=0)
    with pytest.raises(ValueError, match="unknown integrator 'rk45'; known: euler, rk4"):
        envs.PhysicsOptions(integrator="rk45")
    with pytest.raises(ValueError, match="unknown solver 'pgs'; known: newton, cg"):
        envs.PhysicsOptions(solver="pgs")
    with pytest.raises(ValueError, match="timestep must be a positive number of seconds, got -0.01"):
        envs.PhysicsOptions(timestep=-0.01)
    with pytest.raises(ValueError, match="timestep 0.003 does not divide the control time step 0.025"):
        envs.make("walker-run", physics=envs.PhysicsOptions(timestep=0.003))


def test_custom_timestep_keeps_control_time():
    env = envs.make("walker-run", physics=envs.PhysicsOptions(timestep=0.005))
    assert env.n_substeps == 5 and env.mj_model.opt.timestep == 0.005
    assert envs.make("walker-run").n_substeps == 10 and envs.make("cartpole-swingup").n_substeps == 1


@pytest.fixture(scope="module")
def acrobot():
    return envs.make("acrobot-swingup")


def test_wrong_action_shape_and_state_shape(acrobot):
    state = jax.jit(acrobot.reset)(jax.random.key(0))
    with pytest.raises(ValueError, match=r"action must have shape \(1,\), got \(2,\)"):
        acrobot.step(state, jnp.zeros(2))
    with pytest.raises(ValueError, match=r"qpos/qvel must have shapes \(2,\) and \(2,\)"):
        acrobot.reset_to(jnp.zeros(3), jnp.zeros(2))


def test_state_fields_and_time_limit(acrobot):
    """500 agent steps of action repeat 2 = 1000 dm_control steps; done exactly at the last one."""

    def episode(key):
        state = acrobot.reset(key)

        def body(state, _):
            state = acrobot.step(state, jnp.ones(1))
            return state, (state.done, state.reward, state.t)

        return state, jax.lax.scan(body, state, None, length=acrobot.episode_length)[1]

    first, (done, reward, t) = jax.jit(episode)(jax.random.key(3))
    assert first.obs.shape == (6,) and first.clean_obs.shape == (6,)
    assert first.reward.shape == () and first.done.dtype == jnp.bool_ and not bool(first.done)
    assert float(first.dt) == 1.0 and int(first.t) == 0
    done = np.asarray(done)
    assert not done[:-1].any() and done[-1]
    np.testing.assert_array_equal(np.asarray(t), np.arange(1, 501))
    reward = np.asarray(reward)
    assert np.all((reward >= 0) & (reward <= 2.0))  # two dm_control rewards in [0, 1] per agent step


def test_reset_matches_reset_to_of_sampled_state(acrobot):
    """reset(key) starts where reset_start(key) says: the state drawn from the key's first half (a different
    state from the whole key's), the corruptions seeded by its second."""
    key = jax.random.key(11)
    state = jax.jit(acrobot.reset)(key)
    qpos, qvel, k_obs = acrobot.reset_start(key)
    k_init, k_second = jax.random.split(key)
    np.testing.assert_array_equal(np.asarray(qpos), np.asarray(acrobot.initial_qpos_qvel(k_init)[0]))
    np.testing.assert_array_equal(jax.random.key_data(k_obs), jax.random.key_data(k_second))
    assert not np.allclose(np.asarray(qpos), np.asarray(acrobot.initial_qpos_qvel(key)[0]))
    again = jax.jit(acrobot.reset_to)(qpos, qvel, k_obs)
    np.testing.assert_allclose(np.asarray(state.obs), np.asarray(again.obs), atol=1e-6)
    np.testing.assert_allclose(np.asarray(state.physics.qpos), np.asarray(qpos), atol=1e-6)


# walker compiles with XLA's optimisations (conftest): under jax_disable_most_optimizations a restarted walker's qpos
# differs by 1 ulp between the reset inside step_or_reset and reset's own program; cartpole's agree either way
@pytest.mark.parametrize("task,options", [pytest.param("walker-run", {}, marks=pytest.mark.full_optimisation),
                                          ("cartpole-swingup", {"obs_noise": 0.1, "delay": 2})])
def test_step_or_reset_is_a_step_or_a_reset(task, options):
    """The training loop's one physics program (Env.step_or_reset) gives what step gives where an environment runs
    on and what reset gives where it restarts: observations, rewards, counters, keys, corruption state and
    qpos/qvel exactly; forces and other derived fields of a restarted one to float32 rounding (its forward pass
    compiles inside another program). Walker: Euler, contacts, velocity sensors; cartpole: RK4, noise and delay."""
    env = envs.make(task, **options)
    reset = jax.jit(jax.vmap(env.reset))  # three programs in all (one compilation each)
    state = reset(jax.random.split(jax.random.key(1), 2))
    actions = jax.random.uniform(jax.random.key(2), (2, env.action_size), minval=-1, maxval=1)
    restart, keys = jnp.array([True, False]), jax.random.split(jax.random.key(3), 2)
    got = jax.jit(jax.vmap(env.step_or_reset))(state, actions, restart, keys)
    expected = (reset(keys), jax.jit(jax.vmap(env.step))(state, actions))
    exact_physics = {"qpos", "qvel", "ctrl", "time"}
    for i, want in enumerate(expected):  # env 0 restarted, env 1 stepped
        for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(got), jax.tree_util.tree_leaves(want),
                                strict=True):
            if jnp.issubdtype(a.dtype, jax.dtypes.prng_key):
                a, b = jax.random.key_data(a), jax.random.key_data(b)
            a, b, name = np.asarray(a[i]), np.asarray(b[i]), jax.tree_util.keystr(path)
            if not name.startswith(".physics") or name.split(".")[-1] in exact_physics or i == 1:
                np.testing.assert_array_equal(a, b, err_msg=f"env {i} {name}")
            else:
                np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4, err_msg=f"env {i} {name}")
    assert int(got.t[0]) == 0 and int(got.t[1]) == int(state.t[1]) + 1 and float(got.reward[0]) == 0.0


def test_physics_is_traced_once_per_env_and_shapes_for_every_program(monkeypatch):
    """``step_or_reset`` is one jitted function per environment (env.py, ``_traced_once``): the programs that call it
    with the same per-environment argument shapes (the trainer's seed and training chunks; here two vmapped
    programs and an unbatched one, since vmap traced it at those shapes) reuse one trace, and another Env traces
    anew. build_loop evaluates with the training Env itself when the evaluation's observation options are the
    training's, so its evaluation reuses that trace too."""
    from lnnmpc.envs.env import Env
    from lnnmpc.train.config import TrainConfig
    from lnnmpc.train.setup import build_loop

    traces = []
    checked = Env._checked_action
    monkeypatch.setattr(Env, "_checked_action", lambda self, action: traces.append(self) or checked(self, action))
    env = envs.make("cartpole-swingup", remove_vel=True)  # an Env of this test's own: no earlier trace of it
    state = jax.eval_shape(jax.vmap(env.reset), jax.random.split(jax.random.key(0), 3))
    args = (state, jnp.zeros((3, env.action_size)), jnp.zeros(3, bool), jax.random.split(jax.random.key(1), 3))
    jax.jit(jax.vmap(env.step_or_reset)).trace(*args)
    jax.jit(lambda *a: jax.vmap(env.step_or_reset)(*a).reward.sum()).trace(*args)  # another program, same step
    assert traces == [env]
    one = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), state)
    jax.jit(env.step_or_reset).trace(one, args[1][0], args[2][0], args[3][0])  # unbatched: vmap traced these shapes
    assert traces == [env]
    other = envs.make("cartpole-swingup", remove_vel=True)  # equal options, another Env: its own trace
    jax.jit(jax.vmap(other.step_or_reset)).trace(*args)
    assert traces == [env, other]
    base = dict(task="cartpole-swingup", agent="tdmpc2", small=True, steps=1000, seed_steps=500)
    loop = build_loop(TrainConfig(**base))
    assert loop.eval_env is loop.env
    noisy = build_loop(TrainConfig(**base, eval_obs="noise=0.1"))
    assert noisy.eval_env is not noisy.env and noisy.eval_env.corruption != noisy.env.corruption
