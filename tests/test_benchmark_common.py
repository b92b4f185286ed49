"""benchmarks/common.py: the device's short name in output paths, and atomic JSON writes."""

import json
import sys
from pathlib import Path

import jax
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import common  # noqa: E402


@pytest.mark.parametrize("kind, platform, tag", [
    ("NVIDIA H100 80GB HBM3", "gpu", "h100"),
    ("NVIDIA H200", "gpu", "h200"),
    ("NVIDIA A100-SXM4-80GB", "gpu", "a100"),
    ("NVIDIA GeForce RTX 4090", "gpu", "nvidia-geforce-rtx-4090"),
    ("cpu", "cpu", "cpu"),
])
def test_device_tag_names_the_card(kind, platform, tag):
    assert common.device_tag(kind, platform) == tag


def test_write_json_expands_the_device_and_returns_the_path(tmp_path):
    device = jax.devices()[0]
    tag = common.device_tag(device.device_kind, device.platform)  # "cpu" on the CPU backend (tested above)
    written = common.write_json(str(tmp_path / "sub" / "{device}-run-update.json"), {"update_ms": 1.5})
    assert written == str(tmp_path / "sub" / f"{tag}-run-update.json")
    assert json.loads(Path(written).read_text()) == {"update_ms": 1.5}
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == [f"{tag}-run-update.json"]  # no temp file left
    plain = common.write_json(str(tmp_path / "plain.json"), {})
    assert plain == str(tmp_path / "plain.json") and Path(plain).exists()


def test_environment_info_records_the_code_commit(monkeypatch):
    """Every benchmark JSON names the code it measured (the snapshot's commit on a device batch)."""
    from lnnmpc.train import provenance

    monkeypatch.setattr(common, "git_state", lambda: {"commit": "abc123", "dirty": False, "snapshot": "/s"})
    info = common.environment_info()
    assert info["git"] == {"commit": "abc123", "dirty": False, "snapshot": "/s"}
    monkeypatch.undo()
    assert common.environment_info()["git"] == provenance.git_state()
