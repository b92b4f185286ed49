"""MuJoCo models from dm_control's own XML, physics profiles, and the MJX control step.

Two named profiles:

* ``"exact"`` keeps dm_control's options: solver iterations, line search, integrator (RK4 for cartpole and
  acrobot, Euler for walker) and Euler damping. Only the energy flag is cleared: MJX cannot compute energy and
  none of these tasks reads it. With ``jax_enable_x64`` this steps like ``dm_control.suite.load`` to ~1e-10.
* ``"fast"`` (the training default) only lowers the constraint solver's effort and runs its iterations unrolled
  (:mod:`lnnmpc.envs.solver`: MJX's iterates without the ``while_loop``); integrators, time steps and contact
  geometry stay dm_control's, so the agent learns dm_control's dynamics:

  - cartpole: Newton ``iterations=2``, ``ls_iterations=2`` (dm_control: 100 / 50). The slider limit is the only
    constraint; two iterations resolve the cart hitting the end of the rail exactly as ``exact`` does, one does
    not (the pole's angular velocity is then off by ~0.5).
  - acrobot: constraints are disabled in dm_control's XML, so the solver never runs; settings are moot.
  - walker: Newton ``iterations=4``, ``ls_iterations=4``. Matches ``exact`` to 1e-6 through the first ground
    contacts and gives the same random-action returns. Weaker settings break the physics: 1 iteration blows up
    (velocities grow without bound, NaN within ~100 agent steps of random actions), 2 / 4 gives unphysical
    velocities (|qvel| > 200) and +25% random-action return, 3 / 4 drifts to 1e-2 within two agent steps; a
    0.005 s time step moves positions by 0.05 after one agent step. See ``tests/test_env_fast.py`` and
    ``benchmarks/results/``.

Any other combination can be given as a :class:`PhysicsOptions`.
"""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

PROFILES = ("exact", "fast")
INTEGRATORS = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4}
SOLVERS = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG}


@dataclasses.dataclass(frozen=True)
class PhysicsOptions:
    """Changes applied to dm_control's compiled model; ``None`` keeps dm_control's value.

    Attributes:
      iterations: constraint solver iterations (dm_control: 100).
      ls_iterations: line-search iterations (dm_control: 50).
      integrator: "euler" or "rk4".
      solver: constraint solver, "newton" (dm_control's) or "cg".
      disable_eulerdamp: turn off implicit joint damping in the Euler integrator.
      max_contact_points: MJX cap on contacts kept per step (walker only has contacts).
      timestep: physics time step in seconds; must divide dm_control's control time step (the number of
        physics steps per control step is adjusted so that control time is unchanged).
      unrolled_solver: run the solver's iterations as straight-line code instead of MJX's ``while_loop``
        (same iterates, no per-iteration host round trip; see :mod:`lnnmpc.envs.solver`). Meant for few
        iterations: compile time grows with ``iterations``.
    """

    iterations: int | None = None
    ls_iterations: int | None = None
    integrator: str | None = None
    solver: str | None = None
    disable_eulerdamp: bool = False
    max_contact_points: int | None = None
    timestep: float | None = None
    unrolled_solver: bool = False

    def __post_init__(self):
        if self.timestep is not None and not (isinstance(self.timestep, float | int) and self.timestep > 0):
            raise ValueError(f"PhysicsOptions.timestep must be a positive number of seconds, got {self.timestep!r}")
        for name in ("iterations", "ls_iterations", "max_contact_points"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"PhysicsOptions.{name} must be an int >= 1 or None, got {value!r}")
        if self.solver is not None and self.solver not in SOLVERS:
            raise ValueError(f"unknown solver {self.solver!r}; known: {', '.join(SOLVERS)}")
        if self.integrator is not None and self.integrator not in INTEGRATORS:
            raise ValueError(
                f"unknown integrator {self.integrator!r}; known: {', '.join(INTEGRATORS)}"
            )


# The "fast" profile per domain (see the module docstring for why each setting is safe).
FAST_PROFILES = {
    "cartpole": PhysicsOptions(iterations=2, ls_iterations=2, unrolled_solver=True),
    "acrobot": PhysicsOptions(iterations=1, ls_iterations=4),  # constraints disabled: the solver never runs
    "walker": PhysicsOptions(iterations=4, ls_iterations=4, unrolled_solver=True),
}


def resolve_profile(physics: str | PhysicsOptions, domain: str) -> PhysicsOptions:
    """Turns a profile name ("exact", "fast") or an options object into :class:`PhysicsOptions` for ``domain``."""
    if isinstance(physics, PhysicsOptions):
        return physics
    if physics == "exact":
        return PhysicsOptions()
    if physics == "fast":
        return FAST_PROFILES[domain]
    raise ValueError(f"unknown physics profile {physics!r}; known: {', '.join(PROFILES)}")


def _dm_control_xml(domain: str) -> tuple[str, dict[str, bytes]]:
    """Reads ``<domain>.xml`` and the common assets from the installed dm_control package.

    Reads the files directly instead of importing ``dm_control.suite``, which would initialise a rendering
    backend; the bytes are those ``suite.<domain>.get_model_and_assets()`` returns.
    """
    import dm_control

    suite_dir = os.path.join(os.path.dirname(dm_control.__file__), "suite")
    with open(os.path.join(suite_dir, f"{domain}.xml")) as f:
        xml = f.read()
    assets = {}
    for name in ("materials.xml", "skybox.xml", "visual.xml"):
        with open(os.path.join(suite_dir, "common", name), "rb") as f:
            assets[f"./common/{name}"] = f.read()
    return xml, assets


def _with_contact_cap(xml: str, max_contact_points: int) -> str:
    custom = (
        f'<custom><numeric name="max_contact_points" data="{max_contact_points}"/>'
        f'<numeric name="max_geom_pairs" data="{max_contact_points}"/></custom>'
    )
    return xml.replace("</mujoco>", custom + "</mujoco>")


@functools.cache
def load_model(domain: str, options: PhysicsOptions) -> mujoco.MjModel:
    """Compiles dm_control's XML for ``domain`` and applies ``options`` (a new MjModel, cached)."""
    xml, assets = _dm_control_xml(domain)
    if options.max_contact_points is not None:
        xml = _with_contact_cap(xml, options.max_contact_points)
    model = mujoco.MjModel.from_xml_string(xml, assets)
    # MJX cannot compute energy (NotImplementedError in put_model); no task here reads it.
    model.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    if options.iterations is not None:
        model.opt.iterations = options.iterations
    if options.ls_iterations is not None:
        model.opt.ls_iterations = options.ls_iterations
    if options.timestep is not None:
        model.opt.timestep = options.timestep
    if options.integrator is not None:
        model.opt.integrator = INTEGRATORS[options.integrator]
    if options.solver is not None:
        model.opt.solver = SOLVERS[options.solver]
    if options.disable_eulerdamp:
        model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)
    return model


def substeps_per_control_step(dm_control_substeps: int, dm_control_timestep: float, timestep: float) -> int:
    """Physics steps per control step when the physics time step changes (control time step unchanged)."""
    control_dt = dm_control_substeps * dm_control_timestep
    n = round(control_dt / timestep)
    if n < 1 or abs(n * timestep - control_dt) > 1e-9:
        raise ValueError(
            f"timestep {timestep} does not divide the control time step {control_dt}; "
            f"allowed: {control_dt}/k for integer k >= 1"
        )
    return n


def put_model(model: mujoco.MjModel) -> mjx.Model:
    """Places the model on the default JAX device (float64 when ``jax_enable_x64`` is on)."""
    return mjx.put_model(model, impl="jax")


def sync_kinematics(mx: mjx.Model, data: mjx.Data, with_velocity_sensors: bool) -> mjx.Data:
    """Recomputes position- (and optionally velocity-sensor) fields from the current qpos/qvel.

    ``mjx.step`` leaves xpos/xmat/site_xpos from before integration; dm_control re-syncs them with
    ``mj_step1`` before reading observations and rewards. ``with_velocity_sensors`` also refreshes the
    velocity sensors (walker's ``torso_subtreelinvel``), which need the com-based quantities.
    """
    data = mjx.kinematics(mx, data)
    if with_velocity_sensors:
        data = mjx.com_pos(mx, data)
        data = mjx.com_vel(mx, data)
        data = mjx.sensor_vel(mx, data)
    return data


def control_step(
    mx: mjx.Model, data: mjx.Data, action: jax.Array, n_substeps: int, with_velocity_sensors: bool,
    restart: jax.Array | None = None, fresh: mjx.Data | None = None,
) -> mjx.Data:
    """One dm_control control step: set ``ctrl``, take ``n_substeps`` physics steps, re-sync kinematics.

    With ``restart`` (bool scalar) and ``fresh`` (:func:`fresh_data`): where ``restart`` is True the result is
    instead ``fresh``'s forward dynamics (what :func:`data_from_state` returns, kinematics re-synced). Each substep
    then runs one forward pass for both cases (``mjx.step`` is a forward pass and an integration), so a program
    that may restart an environment holds the forward dynamics once instead of twice (a walker reset's forward
    pass is three quarters of a step's operations).

    Args:
      action: (nu,) raw action; MuJoCo clamps it to ctrlrange internally, like dm_control.
    """
    data = data.replace(ctrl=action.astype(data.ctrl.dtype))

    def substep(d, _):
        if restart is None:
            return mjx.step(mx, d), None
        d = mjx.forward(mx, select(restart, fresh, d))
        return select(restart, d, _integrate(mx, d)), None

    data, _ = jax.lax.scan(substep, data, None, length=n_substeps)
    return sync_kinematics(mx, data, with_velocity_sensors)


def _integrate(mx: mjx.Model, data: mjx.Data) -> mjx.Data:
    """``mjx.step``'s integration after its forward pass, by the model's integrator."""
    integrator = mujoco.mjtIntegrator(int(mx.opt.integrator))
    if integrator == mujoco.mjtIntegrator.mjINT_EULER:
        return mjx.euler(mx, data)
    if integrator == mujoco.mjtIntegrator.mjINT_RK4:
        return mjx.rungekutta4(mx, data)
    if integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return mjx.implicit(mx, data)
    raise NotImplementedError(f"integrator {integrator.name} is not implemented by MJX")


def select(flag: jax.Array, on_true, on_false):
    """Leaf by leaf ``on_true`` where ``flag`` (bool scalar) is set, else ``on_false`` (pytrees of one structure)."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(flag, a, b), on_true, on_false)


def fresh_data(mx: mjx.Model, qpos: jax.Array, qvel: jax.Array) -> mjx.Data:
    """``mjx.Data`` at (qpos, qvel) before any forward pass (the rest as ``mjx.make_data`` leaves it)."""
    data = mjx.make_data(mx)
    dtype = data.qpos.dtype
    return data.replace(qpos=jnp.asarray(qpos, dtype), qvel=jnp.asarray(qvel, dtype))


def data_from_state(mx: mjx.Model, qpos: jax.Array, qvel: jax.Array) -> mjx.Data:
    """Fresh ``mjx.Data`` at (qpos, qvel), as after dm_control's ``reset_context`` (which ends in mj_forward)."""
    return mjx.forward(mx, fresh_data(mx, qpos, qvel))


def joint_info(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    """Static per-joint arrays used by the initial-state samplers."""
    return {
        "type": np.asarray(model.jnt_type).copy(),
        "limited": np.asarray(model.jnt_limited).astype(bool),
        "range": np.asarray(model.jnt_range).copy(),
        "qposadr": np.asarray(model.jnt_qposadr).copy(),
        "qpos0": np.asarray(model.qpos0).copy(),
    }
