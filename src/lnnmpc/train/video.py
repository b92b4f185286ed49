"""``make video RUN=<folder>``: one evaluation episode rendered offscreen to MP4 or GIF, with the return overlaid;
``make video RUN=<folder> FILMS=N FALLS=R``: N episodes at once, keeping the films of those that ended below R;
``ACTOR=prior``: the policy prior acts alone instead of the MPPI planner (:mod:`lnnmpc.agents.actor`).

The episode runs on dm_control's simulator (:mod:`lnnmpc.train.dm_backend`, the simulator a policy trained on
MJX must transfer to) with the run's evaluation corruptions; after every agent step MuJoCo's renderer draws the
scene from the task's first camera. Rendering needs an offscreen OpenGL: ``MUJOCO_GL=egl`` (Mesa's EGL works
without a display or GPU; set by the CLI unless already set) or ``osmesa``; it must be chosen before MuJoCo is
imported. Frames are encoded at real time (1 / (control timestep × action repeat) frames per second): MP4 with
the ffmpeg binary of ``imageio-ffmpeg``, GIF with Pillow.
"""

from __future__ import annotations

import os
import sys

import jax
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from lnnmpc.agents.actor import with_actor
from lnnmpc.train.config import ConfigError, parse_obs, require_int
from lnnmpc.train.evaluate import check_observation_size, load_policy, require_actor

FORMATS = ("mp4", "gif")


def overlay(frame: np.ndarray, lines: list[str]) -> np.ndarray:
    """The frame (H, W, 3) uint8 with ``lines`` of text drawn on a dark band at the top."""
    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image, "RGBA")
    font = ImageFont.load_default(size=max(10, frame.shape[0] // 20))
    height = sum(draw.textbbox((0, 0), line, font=font)[3] + 2 for line in lines) + 6
    draw.rectangle((0, 0, frame.shape[1], height), fill=(0, 0, 0, 150))
    y = 3
    for line in lines:
        draw.text((5, y), line, fill=(255, 255, 255, 255), font=font)
        y += draw.textbbox((0, 0), line, font=font)[3] + 2
    return np.asarray(image)


def encode(frames: list[np.ndarray], path: str, fps: float) -> str:
    """Writes frames (H, W, 3) uint8 to ``path`` (.mp4 via imageio-ffmpeg, .gif via Pillow); returns the path."""
    kind = os.path.splitext(path)[1].lstrip(".").lower()
    if kind not in FORMATS:
        raise ConfigError(f"video file {path!r}: use one of {', '.join('.' + f for f in FORMATS)}")
    if not frames:
        raise ValueError("no frames to encode")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if kind == "gif":
        images = [Image.fromarray(f) for f in frames]
        images[0].save(path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
        return path
    height, width = frames[0].shape[:2]
    writer = _mp4_writer(path, width, height, fps)
    for frame in frames:
        writer.send(np.ascontiguousarray(frame))
    writer.close()
    return path


def _mp4_writer(path: str, width: int, height: int, fps: float):
    """A started imageio-ffmpeg generator that encodes the frames sent to it as H.264 MP4 at ``path``."""
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(path, (width, height), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                         macro_block_size=2, ffmpeg_log_level="error")
    writer.send(None)
    return writer


class _EpisodeWriters:
    """One streaming MP4 writer per episode (``<folder>/episode-<e>.mp4``): frames go to ffmpeg as they are
    drawn, so filming many episodes holds no frames in memory."""

    def __init__(self, folder: str, episodes: int, fps: float):
        os.makedirs(folder, exist_ok=True)
        self.paths = [os.path.join(folder, f"episode-{e}.mp4") for e in range(episodes)]
        self.fps, self.writers = fps, [None] * episodes

    def send(self, episode: int, frame: np.ndarray) -> None:
        if self.writers[episode] is None:
            height, width = frame.shape[:2]
            self.writers[episode] = _mp4_writer(self.paths[episode], width, height, self.fps)
        self.writers[episode].send(np.ascontiguousarray(frame))

    def close(self) -> None:
        for writer in self.writers:
            if writer is not None:
                writer.close()


def record_episodes(run: str, *, episodes: int, below: float | None = None, out: str | None = None,
                    obs: str | dict | None = None, checkpoint: int | None = None, seed_index: int = 0,
                    episode_seed: int = 0, width: int = 320, height: int = 240, max_steps: int | None = None,
                    camera: int = 0, actor: str = "planner") -> dict[int, tuple[float, str]]:
    """Films ``episodes`` deterministic episodes of seed ``seed_index``'s policy at once (episode e starts from
    dm_control's initial state ``episode_seed + e``) into ``out`` (a folder, default
    ``<run>/videos/<checkpoint>/``, ``<checkpoint>-prior/`` when the prior acts) as ``episode-<e>.mp4``, and
    keeps the films of the episodes whose return ends below ``below`` (all with None): the falls of a walker
    among many episodes. ``actor``: "planner" (MPPI) or "prior" (the policy prior alone). Returns {episode:
    (return, path)} of the films kept."""
    require_int("episodes", episodes, 1)
    require_actor(actor)
    policy, env, state = _policy_and_env(run, obs, checkpoint, seed_index, max_steps)
    folder = out or os.path.join(run, "videos", _film_name(policy.checkpoint, actor))
    if os.path.splitext(folder)[1].lower().lstrip(".") in FORMATS:
        raise ConfigError(f"filming several episodes (--episodes, --falls-below) writes into a folder, not the "
                          f"file {folder!r}")
    writers = _EpisodeWriters(folder, episodes, _fps(env))
    try:
        returns = _play(policy, env, state, seed_index, episodes, episode_seed, width, height, camera, writers.send,
                        actor)
    finally:
        writers.close()
    kept = keep_films(returns[0], writers.paths, below)
    listed = ", ".join(f"{e} ({r:.1f})" for e, (r, _) in kept.items()) or "none"
    sys.stdout.write(f"returns of {episodes} episodes: mean {returns.mean():.1f}, lowest {returns.min():.1f}; "
                     f"filmed{'' if below is None else f' below {below:g}'}: {listed} -> {folder}\n")
    return kept


def keep_films(returns: np.ndarray, paths: list[str], below: float | None) -> dict[int, tuple[float, str]]:
    """Deletes the films (one per episode, ``returns`` (episodes,)) of the episodes whose return is not below
    ``below`` (None keeps all); returns {episode: (return, path)} of those kept."""
    kept = {}
    for e, path in enumerate(paths):
        if below is None or returns[e] < below:
            kept[e] = (float(returns[e]), path)
        else:
            os.remove(path)
    return kept


def _policy_and_env(run, obs, checkpoint, seed_index, max_steps):
    """The run's policy, its evaluation environment (``obs`` or the run's corruptions, cut at ``max_steps``) and
    seed ``seed_index``'s agent state (a seed axis of one). Sets MUJOCO_GL=egl unless set: offscreen rendering,
    only effective before dm_control is first imported (it is, on the first dm_control episode)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lnnmpc.train.setup import config_env

    policy = load_policy(run, checkpoint)
    config = policy.config
    if not 0 <= seed_index < config.seeds:
        raise ConfigError(f"seed_index {seed_index!r} out of range: the run has seeds 0..{config.seeds - 1}")
    options = dict(config.eval_obs) if obs is None else parse_obs(obs)
    env = config_env(config, options)
    check_observation_size(env, policy)
    if max_steps is not None:
        env = _shortened(env, max_steps)
    return policy, env, jax.tree_util.tree_map(lambda x: x[seed_index:seed_index + 1], policy.agent_state)


def _film_name(checkpoint: int, actor: str) -> str:
    """A film's default name (no extension) under ``<run>/videos/``: the checkpoint, ``-prior`` when the prior acts."""
    return str(checkpoint) if actor == "planner" else f"{checkpoint}-{actor}"


def _play(policy, env, state, seed_index, episodes, episode_seed, width, height, camera, send,
          actor: str) -> np.ndarray:
    """Plays the episodes on dm_control with ``actor`` choosing the actions, sending each agent step's overlaid
    frame as ``send(episode, frame)``; returns the returns (1, episodes). Episode e is the one ``evaluate(run,
    backend="dm_control", seed=episode_seed, actor=actor)`` scores for seed ``seed_index`` as episode e
    (:func:`dm_backend.episode_keys`)."""
    from lnnmpc.train.dm_backend import run_episodes
    from lnnmpc.train.report import StepProgress

    config = policy.config

    def on_step(_, episode, step, physics, total):
        frame = physics.render(height=height, width=width, camera_id=camera)
        acting = "" if actor == "planner" else f" | {actor} alone"
        lines = [f"{config.task} | {config.agent}{acting} | {policy.checkpoint:,} env steps",
                 f"step {step:3d}  return {total:6.1f}"]
        send(episode, overlay(frame, lines))

    return run_episodes(env, with_actor(policy.loop.agent, actor), state, episodes, jax.random.key(episode_seed),
                        seed=episode_seed, seed_ids=[seed_index], on_step=on_step,
                        progress=StepProgress(f"agent steps of {episodes} film(s)"))


def record(run: str, *, out: str | None = None, obs: str | dict | None = None, checkpoint: int | None = None,
           seed_index: int = 0, episode_seed: int = 0, width: int = 320, height: int = 240,
           max_steps: int | None = None, camera: int = 0, actor: str = "planner") -> str:
    """Renders one deterministic episode of seed ``seed_index``'s policy, ``actor`` ("planner" or "prior")
    choosing its actions; returns the video path.

    ``out`` defaults to ``<run>/videos/<checkpoint>.mp4`` (``<checkpoint>-prior.mp4`` when the prior acts).
    ``max_steps`` cuts the episode (agent steps).
    """
    require_actor(actor)
    policy, env, state = _policy_and_env(run, obs, checkpoint, seed_index, max_steps)
    frames = []
    returns = _play(policy, env, state, seed_index, 1, episode_seed, width, height, camera,
                    lambda _, frame: frames.append(frame), actor)
    fps = _fps(env)
    path = encode(frames, out or os.path.join(run, "videos", _film_name(policy.checkpoint, actor) + ".mp4"), fps)
    sys.stdout.write(f"episode return {returns[0, 0]:.1f}; {len(frames)} frames at {fps:g} fps -> {path}\n")
    return path


def _fps(env) -> float:
    """Agent steps per second of simulated time."""
    return 1.0 / env.agent_timestep


def _shortened(env, max_steps: int):
    """The environment with an episode of at most ``max_steps`` agent steps (for short clips)."""
    import dataclasses

    if max_steps < 1:
        raise ConfigError(f"max_steps must be >= 1, got {max_steps!r}")
    spec = dataclasses.replace(env.spec, control_steps=min(env.spec.control_steps, max_steps * env.action_repeat))
    return dataclasses.replace(env, spec=spec)
