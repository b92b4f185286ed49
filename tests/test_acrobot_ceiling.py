"""``lnnmpc.analysis.acrobot_physics`` and ``acrobot_ceiling``: the acrobot's closed-form dynamics against MuJoCo's own
steps of dm_control's model (C, float64), its reward against dm_control's task, the energy against MuJoCo's, and the
planner."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from lnnmpc.analysis import acrobot_ceiling as ac
from lnnmpc.analysis import acrobot_physics as phys


@pytest.fixture(scope="module")
def dm_env():
    return ac.dm_control_envs([0])[0]


@pytest.fixture(scope="module")
def params(dm_env):
    return phys.params_from_model(dm_env.physics.model.ptr)


def _x64(fn, *args):
    with jax.enable_x64(True):
        return np.asarray(fn(*[jnp.asarray(a, jnp.float64) if isinstance(a, np.ndarray) else a for a in args]))


def test_dynamics_match_mujoco_rk4_steps_of_dm_controls_model(dm_env, params):
    model, data = dm_env.physics.model.ptr, mujoco.MjData(dm_env.physics.model.ptr)
    rng = np.random.default_rng(0)
    for _ in range(5):
        qpos, qvel, ctrl = rng.uniform(-np.pi, np.pi, 2), rng.normal(0, 3, 2), rng.uniform(-1.5, 1.5)
        data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, qvel, ctrl
        mujoco.mj_forward(model, data)
        # (the control beyond [-1, 1] clipped as the actuator's range)
        accel = _x64(lambda q, v, u=ctrl: phys.acrobot_accel(params, q, v, u), qpos, qvel)
        np.testing.assert_allclose(accel, data.qacc, rtol=0, atol=1e-10)
        assert model.opt.enableflags & mujoco.mjtEnableBit.mjENBL_ENERGY  # dm_control's XML asks MuJoCo for it
        mujoco_energy = data.energy.sum() - params.g * (params.m1 + params.m2) * data.xpos[1, 2]  # zero: shoulder
        energy = _x64(lambda q, v: phys.mechanical_energy(params, q, v), qpos, qvel)
        assert energy == pytest.approx(mujoco_energy, abs=1e-9)
        q, v = qpos, qvel
        for _ in range(30):
            mujoco.mj_step(model, data)
            q, v = _x64(lambda a, b, u=ctrl: jnp.stack(phys.rk4_step(params, a, b, u)), q, v)
        np.testing.assert_allclose(q, data.qpos, rtol=0, atol=1e-11)
        np.testing.assert_allclose(v, data.qvel, rtol=0, atol=1e-10)


def test_reward_matches_dm_controls_task_and_energy_bounds_are_the_rest_states(dm_env, params):
    physics = dm_env.physics
    rng = np.random.default_rng(1)
    for qpos in [np.zeros(2), np.array([np.pi, 0.0]), np.array([0.15, -0.2]), *rng.uniform(-np.pi, np.pi, (5, 2))]:
        with physics.reset_context():
            physics.data.qpos[:] = qpos
        reward = _x64(lambda q: phys.tip_reward(params, q), qpos)
        assert reward == pytest.approx(dm_env.task.get_reward(physics), abs=1e-14)
    down, up = ac.energy_bounds(params)
    assert down == pytest.approx(_x64(lambda q, v: phys.mechanical_energy(params, q, v), np.array([np.pi, 0.0]),
                                      np.zeros(2)), abs=1e-12)
    assert up == pytest.approx(-down) and up > 0


def test_smooth_noise_interpolates_its_knots_and_config_refuses_impossible_values():
    config = ac.PlannerConfig(horizon=11, samples=3, knot=5)
    noise = np.asarray(ac.smooth_noise(jax.random.PRNGKey(0), config))
    assert noise.shape == (3, 11)
    # knots at steps 0, 5, 10; in between, the straight line
    np.testing.assert_allclose(noise[:, 2], 0.6 * noise[:, 0] + 0.4 * noise[:, 5], atol=1e-6)
    np.testing.assert_allclose(noise[:, 9], 0.2 * noise[:, 5] + 0.8 * noise[:, 10], atol=1e-6)
    assert np.abs(noise[:, 0] - noise[:, 5]).max() > 1e-3
    for bad, message in [({"elites": 5, "samples": 4}, "elites"), ({"horizon": 0}, "horizon"),
                         ({"std_min": 2.0}, "std_min"), ({"energy_weight": -1.0}, "energy_weight")]:
        with pytest.raises(ValueError, match=message):
            ac.PlannerConfig(**bad).validate()


def test_cli_refuses_bad_values_naming_them(capsys):
    assert ac.main(["--elites", "600"]) == 2
    assert "elites (600) must not exceed samples (512)" in capsys.readouterr().err
    assert ac.main(["--episodes", "0"]) == 2
    assert "--episodes must be >= 1" in capsys.readouterr().err


def test_planner_holds_the_chain_upright_in_dm_control(params):
    """From just off the top, a short plan keeps the tip at the target: the planner, the model and dm_control
    agree."""
    envs = ac.dm_control_envs([0])
    physics = envs[0].physics
    with physics.reset_context():
        physics.data.qpos[:] = [0.05, -0.05]
    config = ac.PlannerConfig(horizon=20, samples=64, iterations=2, elites=8, energy_weight=0.0, height_weight=0.0)
    rows = ac.play(envs, config, steps=60, progress=False)
    assert rows[0]["return"] > 0.95 * 60  # one per control step at the target
    assert rows[0]["first_control_step_above_shoulder"] == 0
    with pytest.raises(ValueError, match="steps must be in"):
        ac.play(envs, config, steps=1001, progress=False)
