"""Representation analyses of the thesis's §5.3 (Tables 5.1–5.2, Figures 5.4–5.12) on any run checkpoint.

* :mod:`~lnnmpc.analysis.metrics` (NumPy, float64): ridge regression from [z, z²] to the true state with
  Pearson r per state variable, the cartpole swing-up / balance split, the effective rank of a hidden-state
  matrix, k-step prediction errors of a model rolled forward on its own predictions.
* :mod:`~lnnmpc.analysis.rollout` (JAX): plays deterministic episodes with a run's agent and records latents,
  observations, actions and the true physical state.
* :mod:`~lnnmpc.analysis.projection`: UMAP projections (``umap-learn``, imported on use).
* :mod:`~lnnmpc.analysis.report`: ``python -m lnnmpc.analysis.report RUN`` writes CSVs and figures.
* :mod:`~lnnmpc.analysis.cartpole`, :mod:`~lnnmpc.analysis.acrobot` (on :mod:`~lnnmpc.analysis.episodes`): what each
  seed of a run does with the pole and cart, or the two links, in deterministic episodes.
"""
