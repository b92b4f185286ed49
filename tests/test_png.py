"""Figures as palette PNGs (``lnnmpc.train.png``, ``experiments/scripts/shrink_pngs.py``): the same picture as
matplotlib's own RGBA file, in fewer bytes."""

from __future__ import annotations

import io
import os

import numpy as np
from PIL import Image

from lnnmpc.train.png import save_png

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _figure():
    """A learning-curve-like figure: lines, a shaded band, text, a legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    x = np.linspace(0, 200_000, 50)
    for k in range(4):
        y = 800 * (1 - np.exp(-x / (40_000 * (k + 1))))
        ax.plot(x, y, marker="o", label=f"seed {k}")
        ax.fill_between(x, y - 40, y + 40, alpha=0.2)
    ax.axhline(883.1, linestyle=":", color="0.4", label="thesis")
    ax.set_title("acrobot-swingup")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return fig, plt


def _rgb(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=np.int16)


def test_save_png_writes_the_same_picture_as_a_palette_in_fewer_bytes(tmp_path):
    fig, plt = _figure()
    reference = io.BytesIO()
    fig.savefig(reference, format="png", dpi=90)  # matplotlib's own file (RGBA)
    path = save_png(fig, str(tmp_path / "new" / "curve.png"), dpi=90)
    plt.close(fig)
    data = open(path, "rb").read()
    with Image.open(path) as image:
        assert image.mode == "P" and image.size == Image.open(reference).size
    assert len(data) < 0.6 * reference.getbuffer().nbytes
    diff = np.abs(_rgb(data) - _rgb(reference.getvalue()))
    assert diff.mean() < 1.0 and np.quantile(diff, 0.999) <= 40, (diff.mean(), np.quantile(diff, 0.999))
    assert os.listdir(tmp_path / "new") == ["curve.png"]  # written through a temporary file, none left


def test_transparent_pixels_become_white():
    from lnnmpc.train.png import palette_png

    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[:2] = (200, 30, 30, 255)  # opaque red on top, fully transparent below
    out = np.asarray(palette_png(Image.fromarray(rgba, "RGBA")).convert("RGB"))
    assert (out[:2] == (200, 30, 30)).all() and (out[2:] == 255).all()


def test_shrink_pngs_reencodes_once_and_keeps_palette_files(tmp_path, capsys):
    import importlib.util

    fig, plt = _figure()
    fig.savefig(tmp_path / "old.png", dpi=80)
    plt.close(fig)
    before = (tmp_path / "old.png").read_bytes()
    spec = importlib.util.spec_from_file_location(
        "shrink_pngs", os.path.join(ROOT, "experiments", "scripts", "shrink_pngs.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)  # in this process: no interpreter start-up and imports of its own

    def run():
        assert script.main([str(tmp_path / "old.png")]) == 0
        return capsys.readouterr().out

    first = run()
    after = (tmp_path / "old.png").read_bytes()
    assert f"1 of 1 PNGs re-encoded: {len(before):,} -> {len(after):,} bytes" in first and len(after) < len(before)
    assert Image.open(tmp_path / "old.png").mode == "P"
    assert np.abs(_rgb(after) - _rgb(before)).mean() < 1.0
    assert "0 of 1 PNGs re-encoded" in run() and (tmp_path / "old.png").read_bytes() == after
