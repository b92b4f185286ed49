"""The acrobot's exact equations of motion in closed form, for the acrobot analyses (``acrobot_ceiling``,
``acrobot_trajopt``, ``acrobot_starts``): dm_control's two-link chain with its constants read from the MuJoCo model
(:func:`params_from_model`), the joint accelerations (:func:`acrobot_accel`), one control step as MuJoCo's RK4
integrator takes it (:func:`rk4_step`), the swing-up task's reward (:func:`tip_reward`) and the mechanical energy
(:func:`mechanical_energy`). All but the first are pure ``jax.numpy`` functions over any leading batch shape;
tests/test_acrobot_ceiling.py holds them to MuJoCo's own steps, energies and dm_control's rewards in float64.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

EPISODE_STEPS = 1000  # dm_control control steps per acrobot episode (10 s at 0.01 s)


class AcrobotParams(NamedTuple):
    """The chain's constants: link ``i``'s mass, centre-of-mass distance from its joint, inertia about its centre
    of mass (the hinge axis), the upper link's length, joint damping, actuator gear, gravity and time step."""

    m1: float
    m2: float
    c1: float
    c2: float
    i1: float
    i2: float
    l1: float
    damping: float
    gear: float
    g: float
    dt: float


def params_from_model(model) -> AcrobotParams:
    """Reads :class:`AcrobotParams` from dm_control's acrobot ``MjModel`` (both hinges about y, links along +z)."""
    import mujoco

    def body(name):
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)

    upper, lower = body("upper_arm"), body("lower_arm")

    def axis_inertia(b):  # inertia about the body's y axis through its centre of mass
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, model.body_iquat[b])
        rot = rot.reshape(3, 3)
        return float((rot @ np.diag(model.body_inertia[b]) @ rot.T)[1, 1])

    return AcrobotParams(
        m1=float(model.body_mass[upper]), m2=float(model.body_mass[lower]),
        c1=float(model.body_ipos[upper][2]), c2=float(model.body_ipos[lower][2]),
        i1=axis_inertia(upper), i2=axis_inertia(lower), l1=float(model.body_pos[lower][2]),
        damping=float(model.dof_damping[0]), gear=float(model.actuator_gear[0, 0]),
        g=float(-model.opt.gravity[2]), dt=float(model.opt.timestep))


def mass_matrix(p: AcrobotParams, elbow):
    """The chain's inertia matrix entries ``(m11, m12, m22)``, each ``(...)``, at elbow angles ``(...)``."""
    import jax.numpy as jnp

    coupling = p.m2 * p.l1 * p.c2 * jnp.cos(elbow)
    m22 = p.i2 + p.m2 * p.c2 ** 2
    return p.i1 + p.m1 * p.c1 ** 2 + m22 + p.m2 * p.l1 ** 2 + 2 * coupling, m22 + coupling, m22


def acrobot_accel(p: AcrobotParams, qpos, qvel, ctrl):
    """Joint accelerations ``(..., 2)`` from angles and velocities ``(..., 2)`` (shoulder, elbow; 0 = upright) and
    the elbow's control ``(...)`` (clipped to [-1, 1] as the actuator's range does): ``M(q) qacc = tau - c(q, v)
    + g(q) - damping v`` solved in closed form."""
    import jax.numpy as jnp

    q2 = qpos[..., 1]
    v1, v2 = qvel[..., 0], qvel[..., 1]
    s2 = jnp.sin(q2)
    coupling = p.m2 * p.l1 * p.c2
    m11, m12, m22 = mass_matrix(p, q2)
    s1, s12 = jnp.sin(qpos[..., 0]), jnp.sin(qpos[..., 0] + q2)
    f1 = (coupling * s2 * (2 * v1 * v2 + v2 ** 2) + p.g * ((p.m1 * p.c1 + p.m2 * p.l1) * s1 + p.m2 * p.c2 * s12)
          - p.damping * v1)
    f2 = (p.gear * jnp.clip(ctrl, -1.0, 1.0) - coupling * s2 * v1 ** 2 + p.g * p.m2 * p.c2 * s12
          - p.damping * v2)
    det = m11 * m22 - m12 ** 2
    return jnp.stack([(m22 * f1 - m12 * f2) / det, (m11 * f2 - m12 * f1) / det], axis=-1)


def rk4_step(p: AcrobotParams, qpos, qvel, ctrl):
    """One control step of ``p.dt`` by the classic fourth-order Runge-Kutta rule, as MuJoCo's ``RK4`` integrator
    takes it (the control held): returns the next ``(qpos, qvel)``, each ``(..., 2)``."""
    def deriv(q, v):
        return v, acrobot_accel(p, q, v, ctrl)

    h = p.dt
    dq1, dv1 = deriv(qpos, qvel)
    dq2, dv2 = deriv(qpos + 0.5 * h * dq1, qvel + 0.5 * h * dv1)
    dq3, dv3 = deriv(qpos + 0.5 * h * dq2, qvel + 0.5 * h * dv2)
    dq4, dv4 = deriv(qpos + h * dq3, qvel + h * dv3)
    return (qpos + h / 6 * (dq1 + 2 * dq2 + 2 * dq3 + dq4),
            qvel + h / 6 * (dv1 + 2 * dv2 + 2 * dv3 + dv4))


def tip_reward(p: AcrobotParams, qpos):
    """dm_control's acrobot-swingup reward ``(...)`` of angles ``(..., 2)``: ``tolerance`` of the tip's distance to
    the target (the shoulder plus both links' lengths above it), bounds (0, 0.2), margin 1, Gaussian with 0.1 at
    the margin."""
    import jax.numpy as jnp

    a1, a12 = qpos[..., 0], qpos[..., 0] + qpos[..., 1]
    reach = p.l1 + 2 * p.c2  # tip above the shoulder when upright (the lower link's length)
    dx = p.l1 * jnp.sin(a1) + 2 * p.c2 * jnp.sin(a12)
    dz = reach - p.l1 * jnp.cos(a1) - 2 * p.c2 * jnp.cos(a12)
    distance = jnp.sqrt(dx ** 2 + dz ** 2)
    scaled = jnp.maximum(distance - 0.2, 0.0)
    return jnp.exp(-0.5 * scaled ** 2 * (-2.0 * jnp.log(0.1)))


def mechanical_energy(p: AcrobotParams, qpos, qvel):
    """Kinetic plus potential energy ``(...)`` (potential 0 at the shoulder's height)."""
    import jax.numpy as jnp

    v1, v2 = qvel[..., 0], qvel[..., 1]
    m11, m12, m22 = mass_matrix(p, qpos[..., 1])
    kinetic = 0.5 * (m11 * v1 ** 2 + 2 * m12 * v1 * v2 + m22 * v2 ** 2)
    a1, a12 = qpos[..., 0], qpos[..., 0] + qpos[..., 1]
    potential = p.g * (p.m1 * p.c1 * jnp.cos(a1) + p.m2 * (p.l1 * jnp.cos(a1) + p.c2 * jnp.cos(a12)))
    return kinetic + potential
