"""Recipes (``train --recipe NAME``): each is what its measuring runs recorded and scored, the user's options win
over it, and the CLI and the Makefile pass it on."""

from __future__ import annotations

import dataclasses
import os
import subprocess

import pytest

from lnnmpc.agents.registry import task_default_overrides
from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, TrainConfig
from lnnmpc.train.recipes import RECIPES, recipe_values
from lnnmpc.train.report import eval_table

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# what a run is and how it is kept, not what it learns (the replay's capacity follows the step budget); every other
# TrainConfig field (a new one too) must equal the recipe's in the runs that measured it (``overrides`` on its own)
RUN_FIELDS = {"seeds", "steps", "seed", "replay_capacity", "eval_obs", "eval_every", "eval_episodes", "eval_prior",
              "eval_policies", "checkpoint_every", "keep_checkpoints", "devices", "runs_dir", "name", "out",
              "tensorboard", "wandb", "compile_cache", "compile_ahead", "overrides"}
LEARNING_FIELDS = tuple(f.name for f in dataclasses.fields(TrainConfig) if f.name not in RUN_FIELDS)


def _final_mean(run: str) -> float:
    """The mean return at the run's last evaluation, as its summary.md reports it (equal episodes per seed)."""
    return eval_table(runfolder.read_csv(os.path.join(run, "eval.csv")))[-1]["mean"]


@pytest.mark.parametrize("name", list(RECIPES))
def test_recipe_is_what_its_runs_recorded_and_quotes_what_they_scored(name):
    recipe = RECIPES[name]
    config = TrainConfig(**recipe_values(name, {}))
    assert recipe.runs
    for run in recipe.runs:
        run = os.path.join(ROOT, run)
        saved = runfolder.saved_config(run)  # older runs' config.json completed with today's defaults
        assert {f: getattr(saved, f) for f in LEARNING_FIELDS} == {f: getattr(config, f) for f in LEARNING_FIELDS}, run
        assert saved.overrides == task_default_overrides(config.agent, config.task, config.overrides), run
        assert f"{_final_mean(run):.1f}" in recipe.measured, run  # every run's final mean is quoted


def test_recipe_values_leave_the_users_options_and_settings_in_front():
    values = recipe_values("sparse", {"envs": 2, "seeds": 3, "overrides": ["lambda_=0.5", "num_q=5"]})
    assert values["task"] == "cartpole-swingup-sparse" and values["agent"] == "cfc-op-det"
    assert values["envs"] == 2 and values["seeds"] == 3 and values["seed_steps"] == 20_000
    assert values["overrides"] == {"lambda_": 0.5, "lr_decay_begin": 50_000, "lr_decay_end": 100_000,
                                   "lr_final_scale": 0.1, "num_q": 5}
    assert recipe_values("remove-vel", {"obs": "noise=0.1"})["obs"] == "noise=0.1"  # the given option, whole
    assert recipe_values("acrobot", {})["overrides"]["latent_head"] == "simnorm"
    with pytest.raises(ConfigError, match="unknown recipe 'sprase'; known: sparse, remove-vel, acrobot"):
        recipe_values("sprase", {})
    recipe = RECIPES["sparse"]
    with pytest.raises(ConfigError, match=r"recipe 'x': unknown training settings \['env'\]; known: .*envs"):
        dataclasses.replace(recipe, name="x", train={"env": 8})
    with pytest.raises(ConfigError, match="recipe 'x': unknown task 'cartpole-swing'; known: .*cartpole-swingup"):
        dataclasses.replace(recipe, name="x", task="cartpole-swing")


def test_cli_trains_from_a_recipe_and_lists_them(tmp_path, capsys):
    from lnnmpc.train.cli import main

    run = tmp_path / "run"
    main(["train", "--recipe", "remove-vel", "--small", "--seeds", "2", "--set", "num_q=2", "--out", str(run),
          "--check"])
    out = capsys.readouterr().out
    assert "cartpole-swingup, cfc-zp-det, 2 seed(s) x 8 env(s), 200,000 env steps, obs novel" in out
    assert ("agent overrides: lr_decay_begin=50000, lr_decay_end=100000, lr_final_scale=0.1, num_q=2, plan_horizon=3, "
            "rollout_steps=3, rollout_stride=3\n") in out
    assert capsys.readouterr().err == ""  # measured on that task and agent: no note
    main(["train", "--recipe", "sparse", "--small", "--task", "cartpole-swingup", "--out", str(run), "--check"])
    out, err = capsys.readouterr()
    assert err == ("note: recipe 'sparse' was measured on cartpole-swingup-sparse with cfc-op-det; this run trains "
                   "cartpole-swingup with cfc-op-det\n")
    assert "cartpole-swingup, cfc-op-det, 1 seed(s) x 8 env(s)" in out
    assert "seed phase: 20,000 env steps of colored noise over each episode, spectrum 1/f^1, clipped" in out
    main(["train", "--recipe", "acrobot", "--small", "--out", str(run), "--check", "--eval-policies"])  # builds
    out = capsys.readouterr().out
    assert "acrobot-swingup, cfc-zp-det, 1 seed(s) x 16 env(s)" in out
    assert "10 episode(s) per seed, each policy kept in policies/\n" in out  # --eval-policies, said
    main(["recipes"])
    listing = capsys.readouterr().out
    for recipe in RECIPES.values():
        assert f"{recipe.name}\n  {recipe.flags()}\n  measured: {recipe.measured}" in listing
    assert ("--task cartpole-swingup --agent cfc-zp-det --envs 8 --obs remove_vel=1 --set rollout_steps=3"
            in listing)
    for argv, message in ((["train", "--recipe", "sparse", "--resume", str(run)], "--recipe starts a new run"),
                          (["train", "--recipe", "nope", "--check"], "unknown recipe 'nope'")):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2 and message in capsys.readouterr().err


def test_make_train_passes_the_recipe_and_only_the_variables_given():
    def dry_run(*variables: str, env: dict | None = None) -> str:
        result = subprocess.run(["make", "-n", "-s", "train", *variables], cwd=ROOT, capture_output=True,
                                text=True, env={**os.environ, **(env or {})}, check=True)
        return " ".join(result.stdout.replace("\\\n", " ").split())

    out = dry_run("RECIPE=sparse", "SEEDS=3")
    assert "lnnmpc.train.cli train --recipe \"sparse\" --seeds 3 --steps 200000" in out
    assert "--task" not in out and "--agent" not in out and "--envs" not in out and "--obs" not in out
    out = dry_run("RECIPE=sparse", "ENVS=4", "OBS=noise=0.1")
    assert "--envs 4 --obs \"noise=0.1\"" in out and "--eval-obs" not in out
    assert "--task acrobot-swingup" in dry_run("RECIPE=acrobot", env={"TASK": "acrobot-swingup"})
    out = dry_run()  # without a recipe, the defaults as before
    assert "--task walker-run --agent cfc-zp-det --seeds 1 --steps 200000 --envs 1" in out and "--recipe" not in out
