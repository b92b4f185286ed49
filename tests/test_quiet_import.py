"""Importing the environments prints nothing: mujoco-mjx's notice that Warp is missing is dropped, nothing else."""

import subprocess
import sys

from lnnmpc.envs.quiet_import import drop_warp_notices


def test_drop_warp_notices_keeps_other_lines():
    text = ("Failed to import warp: No module named 'warp'\nkeep me\n"
            "Failed to import mujoco_warp: No module named 'warp'\n  Failed to import warp: indented stays\n")
    assert drop_warp_notices(text) == "keep me\n  Failed to import warp: indented stays\n"
    assert drop_warp_notices("") == ""


def test_importing_the_environments_prints_nothing():
    code = "import lnnmpc.envs, mujoco.mjx; assert lnnmpc.envs.quiet_import.mjx is mujoco.mjx"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert done.stdout == ""
