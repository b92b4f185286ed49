"""The studies of the thesis's chapter 5 as declared grids: tasks × agents × corruptions, seeds per run.

A :class:`Study` lists :class:`Condition`\\ s (a task, the corruption it trains under and the corruptions it is
evaluated under) and agents. :func:`expand` turns a study and :class:`GridOptions` into :class:`RunSpec`\\ s, one
per (condition, agent): a :class:`lnnmpc.TrainConfig` whose ``seeds`` are trained together in one compiled
program, in a deterministic run folder

    <runs_dir>/<task>/<agent>/<train tag>-seeds<N>[-envs<M>][-size1][-small][-recipe-<name>]

(no timestamp), so running a study again finds its runs: finished runs are skipped, partial ones resumed by the
trainer. Runs are shared between studies (Figure 5.19 reuses Table 5.3's acrobot ``cfc-zp-det`` run).
:func:`run_status` reads a folder without importing JAX: ``new`` (no config.json), ``finished`` (eval.csv
reaches the budget and a checkpoint exists at that step) or ``partial``.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import re

from lnnmpc.train import runfolder
from lnnmpc.train.config import BACKENDS, ConfigError, TrainConfig, obs_tag, parse_obs, require_int
from lnnmpc.train.recipes import RECIPES, Recipe

STATUSES = ("new", "partial", "finished")


@dataclasses.dataclass(frozen=True)
class Condition:
    """A task trained under ``train_obs`` and evaluated under each of ``eval_obs`` (corruption texts)."""

    task: str
    train_obs: str = ""
    eval_obs: tuple[str, ...] = ("",)


@dataclasses.dataclass(frozen=True)
class Study:
    """A thesis table or figure: conditions × agents; ``horizons``: planning horizons each run is evaluated with
    (empty: the trained horizon only)."""

    name: str
    source: str
    conditions: tuple[Condition, ...]
    agents: tuple[str, ...]
    horizons: tuple[int, ...] = ()


LNN_VARIANTS = ("cfc-zp-det", "cfc-op-det", "cfc-op-stoch", "ltc-zp-det", "ltc-op-det", "ltc-op-stoch")
THESIS_AGENTS = ("tdmpc2", *LNN_VARIANTS)
NOISE_LEVELS = (0.1, 0.2, 0.3)


def _noise(task: str, flicker: float | None = None) -> Condition:
    """Train at σ = 0.1 (and flicker s), evaluate at σ ∈ {0.1, 0.2, 0.3} with the same flicker."""
    extra = f",flicker={flicker:g}" if flicker else ""
    return Condition(task, f"noise=0.1{extra}", tuple(f"noise={s:g}{extra}" for s in NOISE_LEVELS))


def _delay(task: str, n: int) -> Condition:
    return Condition(task, f"delay={n}", (f"delay={n}",))


STUDIES: dict[str, Study] = {study.name: study for study in (
    Study("table5_3", "Table 5.3", tuple(Condition(task) for task in (
        "cartpole-swingup", "cartpole-swingup-sparse", "acrobot-swingup", "walker-run")), THESIS_AGENTS),
    Study("table5_4", "Table 5.4", (Condition("cartpole-swingup", "remove_vel=1", ("remove_vel=1",)),
                                    _noise("cartpole-swingup", flicker=0.2)), THESIS_AGENTS),
    Study("table5_5", "Table 5.5", (_noise("acrobot-swingup"),), THESIS_AGENTS),
    Study("table5_6", "Table 5.6", (_noise("walker-run"),), THESIS_AGENTS),
    Study("fig5_18", "Figure 5.18", tuple(_delay("cartpole-swingup", n) for n in (3, 6, 10))
          + tuple(_delay("walker-run", n) for n in (1, 2, 3)), ("tdmpc2", "ltc-zp-det")),
    Study("fig5_19", "Figure 5.19", (Condition("acrobot-swingup"),), ("cfc-zp-det",), horizons=(1, 3, 5, 10, 16)),
)}


@dataclasses.dataclass(frozen=True)
class GridOptions:
    """How to run a study: budget and seeds per run, agent subset (None: the study's), environments per seed,
    model size (``tdmpc2`` only), CPU smoke-test sizes, where runs live, and the episodes per seed and backend
    of the study's evaluations (training-time evaluations keep the trainer's 10 episodes, so that changing
    ``episodes`` never makes a run folder unresumable).

    ``eval_every``: the training-time evaluation cadence of *new* runs (the trainer evaluates at the end of the
    budget too, which is what the tables read); a run folder that exists keeps the cadence it was created with
    (:func:`saved_eval_every`), since the trainer refuses to resume under another one. A walker-run evaluation
    costs ~20–30 s on an H100, 20 of them about a quarter of a 200K run: a sparser cadence is what lets such a
    run finish inside one 30-minute hold of a lent GPU.

    ``eval_prior``: the runs' training-time evaluations also play their episodes with the policy prior alone
    (``TrainConfig.eval_prior``; eval.csv's ``prior_return``); a run that exists may turn it on when resumed.

    ``recipes``: a run whose task, agent and training corruption match a recipe (:mod:`lnnmpc.train.recipes`)
    trains with that recipe's settings (its environments per seed, noise, seed phase and agent overrides) in a
    folder of its own (``-recipe-<name>``), and the tables read it; the other runs are unchanged."""

    steps: int = 200_000
    seeds: int = 3
    agents: tuple[str, ...] | None = None
    envs: int = 1
    model_size: int = 5
    small: bool = False
    runs_dir: str = os.path.join("runs", "experiments")
    episodes: int = 10
    backend: str = "mjx"
    eval_every: int = 10_000
    eval_prior: bool = False
    recipes: bool = False

    def __post_init__(self):
        for name in ("steps", "seeds", "envs", "episodes", "eval_every"):
            require_int(name, getattr(self, name), 1)
        for name in ("eval_prior", "recipes"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.backend not in BACKENDS:
            raise ConfigError(f"unknown backend {self.backend!r}; known: {', '.join(BACKENDS)}")
        if self.agents is not None:
            object.__setattr__(self, "agents", tuple(self.agents))


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One training run of a study and what to evaluate it under."""

    study: str
    condition: Condition
    agent: str
    config: TrainConfig
    horizons: tuple[int, ...] = ()
    recipe: str = ""  # the recipe whose settings the run trains with (GridOptions.recipes), else empty

    @property
    def folder(self) -> str:
        return self.config.out


def get_study(name: str) -> Study:
    if name not in STUDIES:
        raise ConfigError(f"unknown study {name!r}; known: {', '.join(STUDIES)}")
    return STUDIES[name]


def run_folder(runs_dir: str, task: str, agent: str, train_obs: str, options: GridOptions, recipe: str = "") -> str:
    """The deterministic folder of a run (module docstring); ``recipe``: the name of the recipe it trains with."""
    name = f"{obs_tag(parse_obs(train_obs))}-seeds{options.seeds}"
    name += (f"-envs{options.envs}" if options.envs != 1 else "") + ("-size1" if options.model_size == 1 else "")
    name += ("-small" if options.small else "") + (f"-recipe-{recipe}" if recipe else "")
    return os.path.join(runs_dir, task, agent, name)


def matching_recipe(condition: Condition, agent: str) -> Recipe | None:
    """The recipe measured on ``condition``'s task and training corruption with ``agent`` (None: none)."""
    for recipe in RECIPES.values():
        if (recipe.task, recipe.agent) == (condition.task, agent) and (
                parse_obs(recipe.train.get("obs", {})) == parse_obs(condition.train_obs)):
            return recipe
    return None


def measured_elsewhere(folder: str) -> tuple[str, int] | None:
    """A run of the same condition as ``folder`` (which does not exist) that differs only in its environments
    per seed, and that count: of the sibling folders ``<tag>-seeds<N>[-envs<M>]<suffix>``, the one evaluated the
    furthest (None: none has evaluations). A table filled by runs of several layouts (walker with 16 environments
    per seed, cartpole with 8) is aggregated with one ``--envs``, and still lists every measured cell."""
    parent, name = os.path.split(folder)
    match = re.fullmatch(r"(.+-seeds\d+)(?:-envs\d+)?(.*)", name)
    if match is None or not os.path.isdir(parent):
        return None
    pattern = re.compile(re.escape(match[1]) + r"(?:-envs(\d+))?" + re.escape(match[2]))
    found = [(last_eval_step(os.path.join(parent, other)), other, int(m[1] or 1))
             for other in sorted(os.listdir(parent)) if (m := pattern.fullmatch(other)) and other != name]
    found = [item for item in found if item[0] is not None]
    if not found:
        return None
    _, other, envs = max(found)
    return os.path.join(parent, other), envs


def expand(study: Study, options: GridOptions) -> list[RunSpec]:
    """The study's runs, conditions outer and agents inner; unknown agents in ``options.agents`` are refused."""
    agents = study.agents if options.agents is None else options.agents
    unknown = [a for a in agents if a not in study.agents]
    if unknown:
        raise ConfigError(f"agent(s) {', '.join(unknown)} are not in {study.name}; its agents: "
                          f"{', '.join(study.agents)}")
    specs = []
    for condition in study.conditions:
        for agent in agents:
            recipe = matching_recipe(condition, agent) if options.recipes else None
            settings = {"envs": options.envs, "seed_steps": 5000, "overrides": {}}
            if recipe is not None:
                settings.update({k: v for k, v in recipe.train.items() if k != "obs"},
                                overrides=dict(recipe.overrides))
            settings["seed_steps"] = min(settings["seed_steps"], options.steps)
            folder = run_folder(options.runs_dir, condition.task, agent, condition.train_obs,
                                dataclasses.replace(options, envs=settings["envs"]), recipe.name if recipe else "")
            config = TrainConfig(task=condition.task, agent=agent, seeds=options.seeds, steps=options.steps,
                                 obs=condition.train_obs, model_size=options.model_size, small=options.small,
                                 out=folder, eval_every=saved_eval_every(folder) or options.eval_every,
                                 eval_prior=options.eval_prior, **settings)
            specs.append(RunSpec(study.name, condition, agent, config, study.horizons, recipe.name if recipe else ""))
    return specs


def saved_eval_every(folder: str) -> int | None:
    """The evaluation cadence recorded in a run folder's config.json (None: no readable config there)."""
    try:
        value = runfolder.read_config(folder)["config"]["eval_every"]
    except (ConfigError, OSError, ValueError, KeyError, TypeError):
        return None
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 1 else None


def checkpoint_steps(folder: str) -> list[int]:
    """Environment steps of the complete checkpoints in a run folder (orbax's ``checkpoints/<step>/``)."""
    path = os.path.join(folder, "checkpoints")
    if not os.path.isdir(path):
        return []
    return sorted(int(name) for name in os.listdir(path) if name.isdigit() and os.path.isdir(os.path.join(path, name)))


def last_eval_step(folder: str) -> int | None:
    """The largest env_step in a run's eval.csv (None without evaluations)."""
    path = os.path.join(folder, "eval.csv")
    if not os.path.exists(path):
        return None
    with open(path, newline="") as f:
        steps = [int(row["env_step"]) for row in csv.DictReader(f)]
    return max(steps) if steps else None


def run_status(folder: str, steps: int) -> str:
    """``new``, ``partial`` or ``finished`` (evaluated at >= ``steps`` with a checkpoint at that step)."""
    if not os.path.exists(os.path.join(folder, "config.json")):
        return "new"
    last = last_eval_step(folder)
    return "finished" if last is not None and last >= steps and last in checkpoint_steps(folder) else "partial"


def eval_file(folder: str, step: int, obs: str, backend: str = "mjx", horizon: int | None = None) -> str:
    """Where an evaluation of checkpoint ``step`` is written: ``lnnmpc.evaluate``'s default path, or
    ``evals/horizon<H>-<tag>-<step>.csv`` for a planning-horizon evaluation."""
    prefix = backend if horizon is None else f"horizon{horizon}"
    return os.path.join(folder, "evals", f"{prefix}-{obs_tag(parse_obs(obs))}-{step}.csv")


def describe(specs: list[RunSpec], options: GridOptions) -> list[str]:
    """One line per run for ``--dry-run``: status, folder, training corruption and evaluations."""
    lines = []
    for spec in specs:
        evals = ", ".join(tag or "clean" for tag in spec.condition.eval_obs)
        horizons = f"; planning horizons {', '.join(map(str, spec.horizons))}" if spec.horizons else ""
        lines.append(f"[{run_status(spec.folder, options.steps):8s}] {spec.folder}  train: "
                     f"{spec.condition.train_obs or 'clean'}  eval: {evals}{horizons}")
    return lines
