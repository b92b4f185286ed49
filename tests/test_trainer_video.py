"""The video pipeline without a trained run: overlay, GIF and MP4 encoding; and the TensorBoard writer.
(A real episode rendered with MuJoCo and Mesa EGL is in tests/test_trainer_run.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from lnnmpc.train.config import ConfigError
from lnnmpc.train.video import encode, overlay


def _frames(n=6, h=48, w=64):
    return [np.full((h, w, 3), 40 * i % 255, np.uint8) for i in range(n)]


def test_overlay_draws_text_on_a_band_at_the_top():
    frame = np.full((120, 160, 3), 200, np.uint8)
    out = overlay(frame, ["walker-run | tdmpc2", "step 12  return 34.5"])
    assert out.shape == frame.shape and out.dtype == np.uint8
    band, below = out[:30], out[60:]
    assert (below == 200).all()  # the scene below is untouched
    assert band.mean() < 150 and band.max() >= 250  # darkened band with white (anti-aliased) text


def test_gif_and_mp4_encoding(tmp_path):
    import imageio_ffmpeg

    frames = _frames()
    gif = encode(frames, str(tmp_path / "a.gif"), fps=50)
    with Image.open(gif) as image:
        assert image.n_frames == 6 and image.size == (64, 48) and image.info["duration"] == 20
    mp4 = encode(frames, str(tmp_path / "sub" / "a.mp4"), fps=25)
    reader = imageio_ffmpeg.read_frames(mp4)
    meta = next(reader)
    assert meta["size"] == (64, 48) and meta["fps"] == 25 and len(list(reader)) == 6
    with pytest.raises(ConfigError, match=r"use one of \.mp4, \.gif"):
        encode(frames, str(tmp_path / "a.avi"), fps=25)


def _log_one_row_each(logger) -> None:
    logger.train_rows([{"env_step": 1000, "seed": 0, "episode_return": 12.5, "total_loss": 0.3}])
    logger.eval_rows([{"env_step": 1000, "seed": 0, "episode": 0, "return": 40.0}])
    logger.close()


def test_tensorboard_scalars_are_written_locally(tmp_path):
    from lnnmpc.train.report import ScalarLogger

    logger = ScalarLogger(str(tmp_path))
    _log_one_row_each(logger)
    events = list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    assert len(events) == 1
    data = events[0].read_bytes()
    assert b"eval/return_mean" in data and b"train/total_loss/seed0" in data


def test_wandb_scalars_are_logged_offline_into_the_run_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    from lnnmpc.train.report import WandbLogger

    logger = WandbLogger(str(tmp_path), "lnnmpc-test", {"task": "cartpole-balance", "seeds": 1})
    _log_one_row_each(logger)
    runs = list((tmp_path / "wandb").glob("offline-run-*/run-*.wandb"))
    assert len(runs) == 1
    data = runs[0].read_bytes()
    assert b"eval/return_mean" in data and b"train/total_loss/seed0" in data and b"cartpole-balance" in data
    # The W&B run id follows the run folder, so a resumed run logs into the same W&B run.
    assert runs[0].name == f"run-{logger.run.id}.wandb"
    again = WandbLogger(str(tmp_path), "lnnmpc-test", {})
    assert again.run.id == logger.run.id
    again.close()
