"""Imports ``mujoco.mjx`` without its notice that the optional Warp backend is missing.

mujoco-mjx 3.17 prints ``Failed to import warp: ...`` and ``Failed to import mujoco_warp: ...`` on standard output
at import when the ``warp`` package is absent; this project uses MJX's JAX backend only, so the two lines are
noise in every log and progress display. Anything else the import prints is passed through unchanged.
"""

from __future__ import annotations

import contextlib
import io
import sys

WARP_NOTICES = ("Failed to import warp:", "Failed to import mujoco_warp:")


def drop_warp_notices(text: str) -> str:
    """``text`` without the lines that start with one of :data:`WARP_NOTICES`."""
    return "".join(line for line in text.splitlines(keepends=True) if not line.startswith(WARP_NOTICES))


def import_mjx():
    """``mujoco.mjx``, imported once with the Warp notices dropped from what it prints."""
    if "mujoco.mjx" in sys.modules:
        return sys.modules["mujoco.mjx"]
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            from mujoco import mjx
    finally:
        sys.stdout.write(drop_warp_notices(captured.getvalue()))
    return mjx


mjx = import_mjx()
