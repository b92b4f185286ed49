"""Reproductions of the thesis's chapter 5 (Tables 5.3–5.6, Figures 5.18–5.19) as resumable study grids.

:mod:`~lnnmpc.experiments.grid` declares the studies, :mod:`~lnnmpc.experiments.run` trains, evaluates and
aggregates one (``python -m lnnmpc.experiments.run NAME`` or ``make experiment NAME=...``),
:mod:`~lnnmpc.experiments.aggregate` writes the CSV and Markdown tables beside the thesis's values
(:mod:`~lnnmpc.experiments.thesis`), :mod:`~lnnmpc.experiments.horizon` evaluates other planning horizons.
The package lives under ``src/lnnmpc`` (not the top-level ``experiments/`` folder, which keeps results) so that
it is importable from anywhere once the project is installed, tests included.
"""
