"""lnnmpc: TD-MPC2 with liquid recurrent history encoders, on MJX.

The trainer's Python API (imported on first use, so ``import lnnmpc.envs`` stays light):

* ``lnnmpc.TrainConfig(task=..., ...)``: a frozen, validated run configuration (:mod:`lnnmpc.train.config`).
* ``lnnmpc.train(config)`` / ``lnnmpc.train(resume=run_folder, steps=...)``: train or continue; returns the run
  folder (:mod:`lnnmpc.train.trainer`).
* ``lnnmpc.evaluate(run, obs=..., episodes=10, backend="mjx"|"dm_control", checkpoint=None)``: re-evaluate a
  checkpoint; returns an ``EvalResult`` with ``mean``, ``std``, ``returns`` and the CSV ``path``.
* ``lnnmpc.record_video(run, out=...)``: render an evaluation episode to MP4/GIF.
"""

_API = {"TrainConfig": ("lnnmpc.train.config", "TrainConfig"), "ConfigError": ("lnnmpc.train.config", "ConfigError"),
        "TrainingDiverged": ("lnnmpc.train.trainer", "TrainingDiverged"),
        "evaluate": ("lnnmpc.train.evaluate", "evaluate"), "record_video": ("lnnmpc.train.video", "record")}

__all__ = [*_API, "train"]


def __getattr__(name: str):
    if name == "train":  # the subpackage, callable as the trainer (see lnnmpc/train/__init__.py)
        import importlib

        return importlib.import_module("lnnmpc.train")
    if name in _API:
        import importlib

        module, attr = _API[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'lnnmpc' has no attribute {name!r}")
