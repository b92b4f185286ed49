"""dm_control's cartpole, acrobot and walker tasks: initial states, observations and rewards in JAX.

Each function mirrors the dm_control task code it names (dm_control 1.0.50, `dm_control/suite/<domain>.py`).
Observation functions return dm_control's observation dict as an ordered tuple of (key, array) pairs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from lnnmpc.envs.rewards import tolerance

ObsFn = Callable[[mjx.Data], tuple[tuple[str, jax.Array], ...]]


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """Static description of one dm_control task.

    Attributes:
      domain, task: dm_control names ("walker", "run").
      n_substeps: physics steps per control step (dm_control's `n_sub_steps`).
      control_steps: control steps per episode (time_limit / control_timestep = 1000 here).
      obs_keys: (key, size) in dm_control's observation order; "velocity" is what `remove_vel` drops.
      needs_velocity_sensors: whether rewards read velocity sensors (walker's subtree linear velocity).
    """

    domain: str
    task: str
    n_substeps: int
    obs_keys: tuple[tuple[str, int], ...]
    needs_velocity_sensors: bool
    init: Callable  # (jax key, joint_info dict, nq, nv) -> (qpos (nq,), qvel (nv,))
    observe: Callable  # (mjx.Data, ids dict) -> tuple[(key, array)]
    reward: Callable  # (mjx.Data, action (nu,), ids dict) -> scalar
    control_steps: int = 1000

    @property
    def name(self) -> str:
        return f"{self.domain}-{self.task}".replace("_", "-")


# ----------------------------------------------------------------------------------------------- cartpole
def _cartpole_init(swing_up: bool):
    def init(key, joints, nq, nv):
        k_pos, k_rest, k_vel = jax.random.split(key, 3)
        if swing_up:
            slider = 0.01 * jax.random.normal(k_pos, ())
            hinge = jnp.pi + 0.01 * jax.random.normal(k_rest, ())
        else:
            slider = jax.random.uniform(k_pos, (), minval=-0.1, maxval=0.1)
            hinge = jax.random.uniform(k_rest, (), minval=-0.034, maxval=0.034)
        qpos = jnp.stack([slider, hinge])
        qvel = 0.01 * jax.random.normal(k_vel, (nv,))
        return qpos, qvel

    return init


def _cartpole_observe(data, ids):
    pole_xmat = data.xmat[ids["pole"]]
    position = jnp.stack([data.qpos[0], pole_xmat[2, 2], pole_xmat[0, 2]])  # x, zz, xz
    return (("position", position), ("velocity", data.qvel))


# The sparse cartpole reward's region (dm_control's _CART_RANGE and _ANGLE_COSINE_RANGE): 1 inside, 0 outside.
CART_BOUNDS = (-0.25, 0.25)
UPRIGHT_COSINE_BOUNDS = (0.995, 1.0)


def _cartpole_reward(sparse: bool):
    def reward(data, action, ids):
        cart_position = data.qpos[0]
        pole_cos = data.xmat[ids["pole"], 2, 2]
        if sparse:
            return tolerance(cart_position, CART_BOUNDS) * tolerance(pole_cos, UPRIGHT_COSINE_BOUNDS)
        upright = (pole_cos + 1) / 2
        centered = (1 + tolerance(cart_position, margin=2)) / 2
        small_control = tolerance(action[0], margin=1, value_at_margin=0, sigmoid="quadratic")
        small_control = (4 + small_control) / 5
        small_velocity = (1 + tolerance(data.qvel[1], margin=5)) / 2
        return upright * small_control * small_velocity * centered

    return reward


# ------------------------------------------------------------------------------------------------ acrobot
def _acrobot_init(key, joints, nq, nv):
    qpos = jax.random.uniform(key, (2,), minval=-jnp.pi, maxval=jnp.pi)
    return qpos, jnp.zeros((nv,))


def _acrobot_observe(data, ids):
    arms = data.xmat[ids["arms"]]  # (2, 3, 3): upper_arm, lower_arm
    orientations = jnp.concatenate([arms[:, 0, 2], arms[:, 2, 2]])  # xz (horizontal), zz (vertical)
    return (("orientations", orientations), ("velocity", data.qvel))


def _acrobot_reward(sparse: bool):
    def reward(data, action, ids):
        distance = jnp.linalg.norm(data.site_xpos[ids["target"]] - data.site_xpos[ids["tip"]])
        return tolerance(distance, (0.0, ids["target_radius"]), margin=0.0 if sparse else 1.0)

    return reward


# ------------------------------------------------------------------------------------------------- walker
_STAND_HEIGHT = 1.2


def _walker_init(key, joints, nq, nv):
    """dm_control's `randomize_limited_and_rotational_joints` for hinge/slide joints: limited joints uniform in
    their range, unlimited hinges uniform in [-pi, pi], unlimited slides left at qpos0."""
    hinge, slide = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
    if not np.all(np.isin(joints["type"], (hinge, slide))):
        raise NotImplementedError("walker init only handles hinge and slide joints")
    limited = joints["limited"]
    low = np.where(limited, joints["range"][:, 0], -np.pi)
    high = np.where(limited, joints["range"][:, 1], np.pi)
    randomized = limited | (joints["type"] == hinge)
    u = jax.random.uniform(key, (len(low),), minval=low, maxval=high)
    qpos = jnp.asarray(joints["qpos0"]).at[joints["qposadr"]].set(
        jnp.where(randomized, u, joints["qpos0"][joints["qposadr"]])
    )
    return qpos, jnp.zeros((nv,))


def _walker_observe(data, ids):
    xmat = data.xmat[1:]  # every body but the world
    orientations = jnp.stack([xmat[:, 0, 0], xmat[:, 0, 2]], axis=-1).reshape(-1)
    return (
        ("orientations", orientations),
        ("height", data.xpos[ids["torso"], 2:3]),
        ("velocity", data.qvel),
    )


def _walker_reward(move_speed: float):
    def reward(data, action, ids):
        torso_height = data.xpos[ids["torso"], 2]
        standing = tolerance(torso_height, (_STAND_HEIGHT, float("inf")), margin=_STAND_HEIGHT / 2)
        upright = (1 + data.xmat[ids["torso"], 2, 2]) / 2
        stand_reward = (3 * standing + upright) / 4
        if move_speed == 0:
            return stand_reward
        horizontal_velocity = data.sensordata[ids["subtreelinvel"]]  # torso_subtreelinvel x
        move_reward = tolerance(
            horizontal_velocity,
            (move_speed, float("inf")),
            margin=move_speed / 2,
            value_at_margin=0.5,
            sigmoid="linear",
        )
        return stand_reward * (5 * move_reward + 1) / 6

    return reward


def _spec(domain, task, n_substeps, obs_keys, init, observe, reward, needs_velocity_sensors=False):
    return TaskSpec(domain, task, n_substeps, obs_keys, needs_velocity_sensors, init, observe, reward)


_CARTPOLE_OBS = (("position", 3), ("velocity", 2))
_ACROBOT_OBS = (("orientations", 4), ("velocity", 2))
_WALKER_OBS = (("orientations", 14), ("height", 1), ("velocity", 9))

TASKS: dict[str, TaskSpec] = {
    spec.name: spec
    for spec in (
        _spec("cartpole", "balance", 1, _CARTPOLE_OBS, _cartpole_init(False), _cartpole_observe,
              _cartpole_reward(False)),
        _spec("cartpole", "balance_sparse", 1, _CARTPOLE_OBS, _cartpole_init(False), _cartpole_observe,
              _cartpole_reward(True)),
        _spec("cartpole", "swingup", 1, _CARTPOLE_OBS, _cartpole_init(True), _cartpole_observe,
              _cartpole_reward(False)),
        _spec("cartpole", "swingup_sparse", 1, _CARTPOLE_OBS, _cartpole_init(True), _cartpole_observe,
              _cartpole_reward(True)),
        _spec("acrobot", "swingup", 1, _ACROBOT_OBS, _acrobot_init, _acrobot_observe, _acrobot_reward(False)),
        _spec("acrobot", "swingup_sparse", 1, _ACROBOT_OBS, _acrobot_init, _acrobot_observe,
              _acrobot_reward(True)),
        _spec("walker", "stand", 10, _WALKER_OBS, _walker_init, _walker_observe, _walker_reward(0.0), True),
        _spec("walker", "walk", 10, _WALKER_OBS, _walker_init, _walker_observe, _walker_reward(1.0), True),
        _spec("walker", "run", 10, _WALKER_OBS, _walker_init, _walker_observe, _walker_reward(8.0), True),
    )
}


def model_ids(domain: str, model: mujoco.MjModel) -> dict:
    """Body/site indices (and constants) the observation and reward functions read."""
    body = lambda name: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
    site = lambda name: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)
    if domain == "cartpole":
        return {"pole": body("pole_1")}
    if domain == "acrobot":
        return {
            "arms": np.array([body("upper_arm"), body("lower_arm")]),
            "tip": site("tip"),
            "target": site("target"),
            "target_radius": float(model.site_size[site("target"), 0]),
        }
    if domain == "walker":
        sensor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, "torso_subtreelinvel")
        return {"torso": body("torso"), "subtreelinvel": int(model.sensor_adr[sensor])}
    raise ValueError(f"unknown domain {domain!r}")
