"""Shared test setup: no OpenGL for dm_control (CI has no display), small CPU-only JAX."""

import os

os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("JAX_PLATFORMS", "cpu")
