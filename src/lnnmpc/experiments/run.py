"""``python -m lnnmpc.experiments.run NAME``: train, evaluate and aggregate one study of the thesis's chapter 5.

    python -m lnnmpc.experiments.run table5_3 --dry-run              # list the grid and each run's status
    python -m lnnmpc.experiments.run table5_3 --agents tdmpc2,cfc-zp-det --seeds 3
    python -m lnnmpc.experiments.run fig5_19 --no-train               # evaluate/aggregate what exists
    make experiment NAME=table5_4 [ARGS="--seeds 3 --agents tdmpc2"]

Steps, each resumable: (1) every run of the grid (:mod:`lnnmpc.experiments.grid`) that is not finished is
trained or resumed (``lnnmpc.train`` resumes a folder holding checkpoints); (2) the newest checkpoint of every
run is evaluated under each of the study's evaluation corruptions (``lnnmpc.evaluate``; planning-horizon studies
with :func:`lnnmpc.experiments.horizon.evaluate_horizon`), skipping evaluations whose file exists; (3) the
results are aggregated (:mod:`lnnmpc.experiments.aggregate`) into ``<out>/<NAME>.csv`` and ``<out>/<NAME>.md``
(default ``experiments/results/studies``). Studies: table5_3, table5_4, table5_5, table5_6, fig5_18, fig5_19.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

from lnnmpc.experiments import grid
from lnnmpc.experiments.aggregate import markdown, study_rows, write_csv
from lnnmpc.experiments.figures import write_study_figure
from lnnmpc.experiments.grid import GridOptions, RunSpec
from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, command_status, parse_obs

DEFAULT_OUT = os.path.join("experiments", "results", "studies")


def train_run(spec: RunSpec, steps: int) -> bool:
    """Trains or resumes a run unless it is finished; returns whether training ran."""
    if grid.run_status(spec.folder, steps) == "finished":
        return False
    import lnnmpc

    lnnmpc.train(spec.config)
    return True


def missing_evaluations(spec: RunSpec, options: GridOptions) -> list[tuple[str, int | None]]:
    """(corruption text, planning horizon or None) pairs of the newest checkpoint that have no file yet."""
    steps = grid.checkpoint_steps(spec.folder)
    if not steps:
        return []
    return [(obs, horizon) for obs in spec.condition.eval_obs for horizon in spec.horizons or (None,)
            if not os.path.exists(grid.eval_file(spec.folder, steps[-1], obs, options.backend, horizon))]


def evaluate_run(spec: RunSpec, options: GridOptions) -> int:
    """Runs the missing evaluations of a run's newest checkpoint; returns how many ran."""
    todo = missing_evaluations(spec, options)
    step = grid.checkpoint_steps(spec.folder)[-1] if todo else None
    for obs, horizon in todo:
        if horizon is None:
            import lnnmpc

            lnnmpc.evaluate(spec.folder, obs=obs, episodes=options.episodes, backend=options.backend,
                            checkpoint=step, out=grid.eval_file(spec.folder, step, obs, options.backend))
        else:
            from lnnmpc.experiments.horizon import evaluate_horizon

            evaluate_horizon(spec.folder, horizon, obs=obs, episodes=options.episodes, checkpoint=step)
    return len(todo)


def aggregate(name: str, specs: list[RunSpec], options: GridOptions, out: str) -> tuple[str, ...]:
    """Writes ``<out>/<name>.csv``, ``<out>/<name>.md`` and, once something is measured, the figure
    ``<out>/<name>.png`` (:mod:`lnnmpc.experiments.figures`), each atomically (studies running side by side may
    aggregate at the same time); returns their paths."""
    study = grid.get_study(name)
    rows = study_rows(study, specs, options.steps, options.backend)
    csv_path, md_path = os.path.join(out, f"{name}.csv"), os.path.join(out, f"{name}.md")
    write_csv(csv_path, rows)
    runfolder.write_text(md_path, markdown(study, rows))
    png = write_study_figure(study, specs, rows, os.path.join(out, f"{name}.png"), options.steps, options.backend)
    return (csv_path, md_path) + ((png,) if png else ())


def table_specs(name: str, options: GridOptions) -> list[RunSpec]:
    """The runs a study's tables list: every run of the requested agents (``options.agents``; a missing one shows
    as "not yet run") and the runs of the study's other agents whose folders exist, so that tables filled by
    separate ``--agents`` invocations, or by studies running side by side, show every measured cell. A run whose
    folder for ``options.envs`` does not exist is looked up with other environments per seed
    (:func:`grid.measured_elsewhere`)."""
    study = grid.get_study(name)
    requested = set(options.agents or study.agents)
    specs = []
    for spec in grid.expand(study, dataclasses.replace(options, agents=None)):
        other = None if os.path.isdir(spec.folder) else grid.measured_elsewhere(spec.folder)
        if other is not None:  # the same condition run with another number of environments per seed
            spec = dataclasses.replace(spec, config=dataclasses.replace(spec.config, out=other[0], envs=other[1]))
        if spec.agent in requested or os.path.isdir(spec.folder):
            specs.append(spec)
    return specs


def select_conditions(specs: list[RunSpec], tasks: tuple[str, ...] | None, train_obs: str | None) -> list[RunSpec]:
    """The runs whose task is in ``tasks`` and whose training corruption is ``train_obs`` ("" or "clean": none);
    None keeps all. A value that matches none of the study's conditions is refused, naming the ones it has."""
    if tasks is not None:
        known = sorted({spec.condition.task for spec in specs})
        unknown = [t for t in tasks if t not in known]
        if unknown:
            raise ConfigError(f"task(s) {', '.join(unknown)} are not in this study; its tasks: {', '.join(known)}")
        specs = [spec for spec in specs if spec.condition.task in tasks]
    if train_obs is not None:  # compared as options, so "flicker=0.2,noise=0.1" selects "noise=0.1,flicker=0.2"
        wanted = parse_obs("" if train_obs == "clean" else train_obs)
        known = sorted({spec.condition.train_obs or "clean" for spec in specs})
        specs = [spec for spec in specs if parse_obs(spec.condition.train_obs) == wanted]
        if not specs:
            raise ConfigError(f"no condition trains under {train_obs!r}; the study's: {', '.join(known)}")
    return specs


def run_study(name: str, options: GridOptions, *, out: str = DEFAULT_OUT, dry_run: bool = False,
              train: bool = True, evaluate: bool = True, tasks: tuple[str, ...] | None = None,
              train_obs: str | None = None) -> list[str]:
    """The whole study (module docstring), or the runs of the conditions that ``tasks`` and ``train_obs`` select
    (:func:`select_conditions`; the tables still aggregate every run that exists); ``dry_run`` only lists the
    grid. Returns the lines it printed."""
    all_specs = grid.expand(grid.get_study(name), options)
    specs = select_conditions(all_specs, tasks, train_obs)
    if dry_run:
        lines = [f"{name}: {len(specs)} runs of {options.seeds} seed(s) x {options.steps:,} env steps"]
        return lines + grid.describe(specs, options)
    for spec in specs:
        if train:
            train_run(spec, options.steps)
        if evaluate:
            evaluate_run(spec, options)
    return [f"wrote {path}" for path in aggregate(name, table_specs(name, options), options, out)]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The study command's options (``argv``: the arguments after the program's name; None: sys.argv's)."""
    p = argparse.ArgumentParser(prog="python -m lnnmpc.experiments.run", description=__doc__.split("\n")[0])
    p.add_argument("name", choices=sorted(grid.STUDIES), help="the study")
    p.add_argument("--steps", type=int, default=200_000, help="environment steps per run (default 200000)")
    p.add_argument("--seeds", type=int, default=3, help="seeds per run, trained together (default 3)")
    p.add_argument("--agents", default=None, help="comma-separated subset of the study's agents")
    p.add_argument("--tasks", default=None, help="comma-separated subset of the study's tasks")
    p.add_argument("--train-obs", default=None,
                   help='only the conditions trained under this corruption text (e.g. "noise=0.1,flicker=0.2"; '
                        '"clean": none); --dry-run lists them')
    p.add_argument("--envs", type=int, default=1, help="environments per seed (default 1)")
    p.add_argument("--model-size", type=int, default=5, choices=(1, 5), help="tdmpc2 size in M parameters")
    p.add_argument("--small", action="store_true", help="CPU smoke-test sizes (not the thesis's setting)")
    p.add_argument("--episodes", type=int, default=10, help="evaluation episodes per seed (default 10)")
    p.add_argument("--eval-every", type=int, default=GridOptions.eval_every,
                   help="training-time evaluation cadence of new runs in environment steps (default 10000; the "
                        "budget's end is always evaluated; an existing run keeps its own)")
    p.add_argument("--eval-prior", action="store_true",
                   help="the runs' training-time evaluations also play their episodes with the policy prior alone "
                        "(eval.csv's prior_return)")
    p.add_argument("--recipes", action="store_true",
                   help="runs that match a recipe (`python -m lnnmpc.train.cli recipes`) train with its settings, in "
                        "folders of their own, and fill the tables")
    p.add_argument("--backend", default="mjx", choices=("mjx", "dm_control"))
    p.add_argument("--runs-dir", default=GridOptions.runs_dir, help="where run folders live")
    p.add_argument("--out", default=DEFAULT_OUT, help="where the CSV and Markdown tables go")
    p.add_argument("--dry-run", action="store_true", help="list the grid and the runs' status, run nothing")
    p.add_argument("--no-train", action="store_true", help="only evaluate and aggregate what exists")
    p.add_argument("--aggregate-only", action="store_true", help="only write the tables from existing files")
    return p.parse_args(argv)


def _split(text: str | None) -> tuple[str, ...] | None:
    return None if text is None else tuple(part.strip() for part in text.split(",") if part.strip())


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)

    def study() -> str:
        agents = _split(args.agents)
        options = GridOptions(steps=args.steps, seeds=args.seeds, agents=agents, envs=args.envs,
                              model_size=args.model_size, small=args.small, runs_dir=args.runs_dir,
                              episodes=args.episodes, backend=args.backend, eval_every=args.eval_every,
                              eval_prior=args.eval_prior, recipes=args.recipes)
        return "\n".join(run_study(args.name, options, out=args.out, dry_run=args.dry_run,
                                   train=not (args.no_train or args.aggregate_only),
                                   evaluate=not args.aggregate_only, tasks=_split(args.tasks),
                                   train_obs=args.train_obs))

    return command_status(study)


if __name__ == "__main__":
    sys.exit(main())
