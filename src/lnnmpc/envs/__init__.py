"""dm_control's cartpole, acrobot and walker tasks as pure JAX functions on MJX, with POMDP corruptions."""

# First: imports mujoco.mjx (which the modules below use) without its notice that Warp is missing.
from lnnmpc.envs import quiet_import  # noqa: F401, I001
from lnnmpc.envs.corruptions import OPTIONS, CorruptionConfig, CorruptionState
from lnnmpc.envs.env import Env, EnvState, make
from lnnmpc.envs.physics import PROFILES, PhysicsOptions
from lnnmpc.envs.rewards import tolerance
from lnnmpc.envs.tasks import TASKS

__all__ = [
    "OPTIONS", "PROFILES", "TASKS", "CorruptionConfig", "CorruptionState", "Env", "EnvState",
    "PhysicsOptions", "make", "tolerance",
]
