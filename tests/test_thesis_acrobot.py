"""The thesis's acrobot reward (eq. 4.6) against hand-computed float64 values and dm_control's own reward at the
same physics states; the reference controllers and the CLI on short dm_control episodes."""

import csv

import numpy as np
import pytest
from dm_control import suite

from lnnmpc.analysis import thesis_acrobot


def test_eq_4_6_pays_upright_and_hanging_alike_where_dm_control_pays_only_upright():
    shoulder = np.array([0.0, np.pi, np.pi / 2, np.pi / 3, -np.pi])
    elbow = np.array([0.0, 0.0, np.pi / 2, 2 * np.pi / 3, np.pi])
    np.testing.assert_allclose(thesis_acrobot.thesis_reward(shoulder, elbow), [1.0, 1.0, 0.0, 0.5, 1.0], atol=1e-12)

    env = suite.load("acrobot", "swingup", task_kwargs={"random": 0})
    env.reset()
    dm_reward = {}
    for name, qpos in {"upright": (0.0, 0.0), "hanging": (np.pi, 0.0)}.items():
        with env.physics.reset_context():
            env.physics.named.data.qpos[["shoulder", "elbow"]] = qpos
            env.physics.named.data.qvel[:] = 0.0
        dm_reward[name] = env.task.get_reward(env.physics)
        assert thesis_acrobot.thesis_reward(*qpos) == pytest.approx(1.0)
    assert dm_reward["upright"] == pytest.approx(1.0)
    assert dm_reward["hanging"] < 1e-3


def test_elbow_damping_brakes_the_elbow_where_no_torque_lets_it_swing():
    def elbow_speeds(controller):
        env = suite.load("acrobot", "swingup", task_kwargs={"random": 3})
        env.reset()
        speeds = []
        for _ in range(400):
            env.step(controller(env.physics))
            speeds.append(abs(float(env.physics.named.data.qvel["elbow"][0])))
        return np.array(speeds)

    damped = elbow_speeds(thesis_acrobot.elbow_damping(1.0))
    free = elbow_speeds(thesis_acrobot.controllers(0)["zero"])
    assert damped[-100:].mean() < 0.5 * free[-100:].mean()
    assert np.all(np.abs(thesis_acrobot.elbow_damping(50.0)(_FakePhysics(3.0))) <= 1.0)
    with pytest.raises(ValueError, match="gain must be > 0"):
        thesis_acrobot.elbow_damping(0.0)


class _FakePhysics:
    """Just the attribute path a controller reads: physics.named.data.qvel["elbow"]."""

    def __init__(self, elbow_velocity: float):
        qvel = {"elbow": np.array([elbow_velocity])}
        self.named = type("Named", (), {"data": type("Data", (), {"qvel": qvel})()})()


def test_play_sums_each_steps_rewards_over_the_resulting_angles():
    steps = 30
    dm_return, thesis_return = thesis_acrobot.play(thesis_acrobot.controllers(0)["zero"], episode=2, steps=steps)
    env = suite.load("acrobot", "swingup", task_kwargs={"random": 2})  # the same episode by hand
    env.reset()
    rewards, angles = [], []
    for _ in range(steps):
        rewards.append(env.step(np.zeros(1)).reward)
        angles.append(env.physics.named.data.qpos[["shoulder", "elbow"]].copy())
    angles = np.array(angles)
    assert dm_return == pytest.approx(sum(rewards), rel=1e-12)
    reference = (0.5 * np.abs(np.cos(angles[:, 0])) + 0.5 * np.abs(np.cos(angles[:, 1]))).sum()
    assert thesis_return == pytest.approx(reference, rel=1e-12)
    assert 0 <= thesis_return <= steps


def test_cli_writes_one_row_per_controller_and_episode_and_names_bad_controllers(tmp_path, capsys):
    out = tmp_path / "thesis.csv"
    assert thesis_acrobot.main(["--episodes", "2", "--steps", "20", "--controllers", "zero,elbow-damping",
                                "--out", str(out)]) == 0
    with open(out) as file:
        rows = list(csv.DictReader(file))
    assert [(row["controller"], row["episode"]) for row in rows] == [
        ("zero", "0"), ("zero", "1"), ("elbow-damping", "0"), ("elbow-damping", "1")]
    assert all(0 <= float(row["thesis_return"]) <= 20 for row in rows)
    printed = capsys.readouterr().out
    assert "| elbow-damping | 2 |" in printed and "eq. 4.6 return" in printed
    with pytest.raises(SystemExit):
        thesis_acrobot.main(["--controllers", "zero,swing", "--out", str(tmp_path / "x.csv")])
    assert "unknown controller(s) ['swing']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        thesis_acrobot.main(["--episodes", "0", "--out", str(tmp_path / "x.csv")])
    assert "episodes=0" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # past dm_control's episode the environment would restart
        thesis_acrobot.main(["--steps", "1001", "--out", str(tmp_path / "x.csv")])
    assert "steps in 1..1000 (dm_control's episode), got episodes=10, steps=1001" in capsys.readouterr().err
