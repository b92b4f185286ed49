"""``--deterministic`` (``TrainConfig.deterministic``): XLA's deterministic GPU ops, requested through
``XLA_FLAGS`` before JAX starts its backend, refused with a clear error where a GPU backend started without them,
and recorded in the run's configuration and each start's provenance."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import pytest

from lnnmpc.train import setup
from lnnmpc.train.config import ConfigError, TrainConfig, incompatibilities
from lnnmpc.train.setup import DETERMINISTIC_FLAG, enable_deterministic_ops

SRC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "src")


def test_the_cli_sets_the_flag_before_the_backend_starts(tmp_path):
    """In a fresh process, `train --deterministic --check` reaches the flag while no backend has started, XLA
    accepts the flag when the backend then starts (an unknown flag aborts the process), and --check says so."""
    script = textwrap.dedent(f"""
        import os
        from jax._src import xla_bridge
        from lnnmpc.train import setup
        from lnnmpc.train.cli import main

        seen = {{}}
        original = setup.enable_deterministic_ops

        def spy(on):
            seen["started_before"] = xla_bridge.backends_are_initialized()
            original(on)

        setup.enable_deterministic_ops = spy
        main(["train", "--task", "cartpole-balance", "--small", "--deterministic", "--out", {str(tmp_path / "run")!r},
              "--check"])
        print("started before:", seen["started_before"], "| flags:", os.environ.get("XLA_FLAGS"))
    """)
    env = {**os.environ, "PYTHONPATH": SRC, "JAX_PLATFORMS": "cpu",
           "XLA_FLAGS": "--xla_force_host_platform_device_count=1"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert ", XLA deterministic GPU ops\n" in done.stdout
    assert (f"started before: False | flags: --xla_force_host_platform_device_count=1 {DETERMINISTIC_FLAG}"
            in done.stdout)  # the user's flags kept, ours added once


def test_a_started_gpu_backend_without_the_flag_is_refused(monkeypatch):
    jax.devices()  # this test process's backend has started
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_autotune_level=0")
    monkeypatch.setattr(setup.jax, "default_backend", lambda: "gpu")
    with pytest.raises(ConfigError) as error:
        enable_deterministic_ops(True)
    message = str(error.value)
    assert f"XLA_FLAGS={DETERMINISTIC_FLAG}" in message and "gpu backend" in message
    assert "--xla_gpu_autotune_level=0" in message and "--deterministic" in message
    enable_deterministic_ops(False)  # off: nothing to check
    monkeypatch.setenv("XLA_FLAGS", f"--xla_gpu_autotune_level=0 {DETERMINISTIC_FLAG}")
    enable_deterministic_ops(True)  # already there (set before the start): fine
    assert os.environ["XLA_FLAGS"] == f"--xla_gpu_autotune_level=0 {DETERMINISTIC_FLAG}"


def test_a_started_cpu_backend_is_left_alone(monkeypatch):
    jax.devices()
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(setup.jax, "default_backend", lambda: "cpu")
    enable_deterministic_ops(True)
    assert os.environ["XLA_FLAGS"] == ""  # a flag set now would claim what XLA never read


def test_the_setting_is_validated_recorded_and_may_change_on_resume():
    with pytest.raises(ConfigError, match="deterministic must be True or False, got 'yes'"):
        TrainConfig(task="cartpole-balance", deterministic="yes")
    saved = TrainConfig(task="cartpole-balance")
    assert saved.deterministic is False and json.loads(json.dumps(saved.to_dict()))["deterministic"] is False
    old = {k: v for k, v in saved.to_dict().items() if k != "deterministic"}  # a config.json from before the field
    assert TrainConfig.from_dict(old).deterministic is False
    assert incompatibilities(saved, TrainConfig(task="cartpole-balance", deterministic=True)) == []


def test_provenance_records_the_xla_flags(monkeypatch, tmp_path):
    from lnnmpc.train import provenance

    monkeypatch.setenv("XLA_FLAGS", DETERMINISTIC_FLAG)
    assert provenance.device_platform(str(tmp_path / "missing"))["xla_flags"] == DETERMINISTIC_FLAG
    monkeypatch.delenv("XLA_FLAGS")
    assert provenance.device_platform(str(tmp_path / "missing"))["xla_flags"] == ""


def test_eval_and_video_set_the_flag_before_the_backend_starts(tmp_path):
    """`eval --deterministic` and `video --deterministic` in a fresh process: the CLI asks for the flag before any
    backend has started (here both then refuse a folder that is no run, exit status 2, as they would after it);
    without the option the flag is not asked for."""
    script = textwrap.dedent(f"""
        import os
        from jax._src import xla_bridge
        from lnnmpc.train import setup
        from lnnmpc.train.cli import main

        seen = []
        original = setup.enable_deterministic_ops

        def spy(on):
            seen.append((on, xla_bridge.backends_are_initialized()))
            original(on)

        setup.enable_deterministic_ops = spy
        for command in (["eval", "--episodes", "2"], ["video"], ["eval", "--deterministic"],
                        ["video", "--deterministic"]):
            try:
                main([command[0], {str(tmp_path / "no-run")!r}, *command[1:]])
            except SystemExit as stop:
                seen.append(stop.code)
        print("seen:", seen, "| flags:", os.environ.get("XLA_FLAGS"))
    """)
    env = {**os.environ, "PYTHONPATH": SRC, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": ""}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert ("seen: [(False, False), 2, (False, False), 2, (True, False), 2, (True, False), 2] | flags: "
            f"{DETERMINISTIC_FLAG}\n") in done.stdout
    assert done.stderr.count("is not a run folder (no config.json)") == 4


def test_make_eval_and_video_pass_deterministic():
    root = os.path.join(os.path.dirname(__file__), "..")
    for target in ("eval", "video"):
        given = subprocess.run(["make", "-n", "-s", target, "RUN=runs/a", "DETERMINISTIC=1"], cwd=root,
                               capture_output=True, text=True, check=True)
        plain = subprocess.run(["make", "-n", "-s", target, "RUN=runs/a"], cwd=root, capture_output=True, text=True,
                               check=True)
        assert f"lnnmpc.train.cli {target} " in given.stdout and " --deterministic" in given.stdout
        assert "--deterministic" not in plain.stdout
