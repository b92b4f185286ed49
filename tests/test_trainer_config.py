"""Validation of the trainer's configuration before anything compiles: every error names the bad value and the
allowed ones; the CLI exits non-zero with the message."""

from __future__ import annotations

import os

import numpy as np
import pytest

from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, TrainConfig, obs_tag, parse_obs, parse_overrides
from lnnmpc.train.guard import first_non_finite
from lnnmpc.train.references import references, variant
from lnnmpc.train.setup import validate
from lnnmpc.train.sharding import device_count_for


def test_parse_obs_and_overrides():
    assert parse_obs("noise=0.1, flicker=0.2,delay=3,remove_vel=1") == {
        "obs_noise": 0.1, "flicker": 0.2, "delay": 3, "remove_vel": True}
    assert parse_obs("") == {} and parse_obs({"obs_noise": 0.3}) == {"obs_noise": 0.3}
    assert obs_tag(parse_obs("noise=0.1,flicker=0.2")) == "flicker0.2-noise0.1" and obs_tag({}) == "clean"
    assert parse_overrides(["plan_horizon=5", "lr=1e-3", "mode=pure"]) == {
        "plan_horizon": 5, "lr": 0.001, "mode": "pure"}


@pytest.mark.parametrize("values, message", [
    ({"task": "walker-fly"}, "unknown task 'walker-fly'; known: cartpole-balance, "),
    ({"agent": "gru"}, "unknown agent 'gru'; known: tdmpc2"),
    ({"physics": "slow"}, "unknown physics profile 'slow'; known: "),
    ({"model_size": 3}, "model_size must be 1 or 5 (million parameters), got 3"),
    ({"seeds": 0}, "seeds must be an integer >= 1, got 0"),
    ({"steps": 1.5}, "steps must be an integer >= 1, got 1.5"),
    ({"seed_steps": -1}, "seed_steps must be an integer >= 0, got -1"),
    ({"eval_episodes": 0}, "eval_episodes must be an integer >= 1, got 0"),
    ({"checkpoint_every": 0}, "checkpoint_every must be an integer >= 1, got 0"),
    ({"steps": 1000, "seed_steps": 5000}, "steps (1000) must be >= seed_steps (5000)"),
    ({"obs": "blur=1"}, "bad observation option 'blur'; known: noise, obs_noise, flicker, delay, remove_vel"),
    ({"obs": "noise"}, "bad observation option 'noise'; use key=value"),
    ({"obs": "noise=-0.1"}, "obs_noise must be >= 0"),
    ({"obs": "delay=1.5"}, "delay='1.5' is not an integer"),
    ({"eval_obs": "remove_vel=maybe"}, "remove_vel='maybe': use one of 1, true"),
    ({"overrides": ["horizon"]}, "bad --set 'horizon'; use KEY=VALUE"),
    ({"name": "a/b"}, "run name 'a/b' must not contain '/'"),
    ({"wandb": "my project"}, "wandb project 'my project' must be letters, digits, '.', '_' or '-'"),
    ({"compile_ahead": "yes"}, "compile_ahead='yes'; allowed: auto, on, off"),
    ({"eval_prior": "yes"}, "eval_prior must be True or False, got 'yes'"),
    ({"updates_per_step": 0}, "updates_per_step must be an integer >= 1, got 0"),
    ({"action_repeat": 0}, "action_repeat must be an integer >= 1, got 0"),
])
def test_bad_values_are_named_with_the_allowed_ones(values, message):
    with pytest.raises(ConfigError) as error:
        TrainConfig(**{"task": "cartpole-balance", **values})
    assert message in str(error.value)


def test_validation_builds_environments_and_agent_without_compiling(tmp_path):
    small = {"task": "cartpole-balance", "small": True, "out": str(tmp_path / "run")}
    with pytest.raises(ConfigError, match="unknown hyperparameter|no_such_key"):
        validate(TrainConfig(**small, overrides={"no_such_key": 1}))
    with pytest.raises(ConfigError, match="changes the observation size"):
        validate(TrainConfig(**small, eval_obs="remove_vel=1"))
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ConfigError, match=f"output folder '{blocker}/run' is not writable"):
        validate(TrainConfig(**{**small, "out": str(blocker / "run")}))
    with pytest.raises(ConfigError, match="is not a run folder"):
        validate(resume=str(tmp_path))


def test_updates_per_step_reaches_the_loop_and_the_burst_after_the_seed_phase(tmp_path):
    """1,000 seed steps of 2 environments (action repeat 2) are 250 iterations, 500 agent steps: 3 updates each."""
    setup = validate(TrainConfig(task="cartpole-balance", small=True, envs=2, seed_steps=1000, updates_per_step=3,
                                 out=str(tmp_path / "run")), create=False)
    assert setup.seed_iterations == 250 and setup.burst_updates == 1500
    assert setup.loop.config.updates_per_step == 3


def test_action_repeat_reaches_the_environments_and_counts_agent_steps(tmp_path):
    """Action repeat 4: the training and evaluation Envs repeat each action 4 control steps (250 agent steps an
    episode), 1,000 seed steps of 2 environments are 125 iterations (not 250), the configuration's JSON keeps it
    and an evaluation's Env (``config_env``, as ``eval`` and ``video`` build it) is the training one; the default
    (2) builds the same Env as ``envs.make`` without it."""
    import json

    from lnnmpc.train.setup import config_env, shared_env

    config = TrainConfig(task="cartpole-balance", small=True, envs=2, seed_steps=1000, action_repeat=4,
                         out=str(tmp_path / "run"))
    setup = validate(config, create=False)
    assert setup.loop.env.action_repeat == 4 and setup.loop.eval_env is setup.loop.env
    assert setup.loop.env.episode_length == 250 and setup.seed_iterations == 125 and setup.per_iteration == 8
    saved = TrainConfig.from_dict(json.loads(json.dumps(config.to_dict())))
    assert saved.action_repeat == 4 and config_env(saved, saved.eval_obs) is setup.loop.env
    default = TrainConfig(task="cartpole-balance")
    assert config_env(default, {}) is shared_env("cartpole-balance", "fast", {})
    assert config_env(default, {}).action_repeat == 2


def test_devices_for_seeds():
    assert device_count_for(8, 2) == 2 and device_count_for(3, 2) == 1 and device_count_for(6, 4) == 3
    assert device_count_for(1, 8) == 1
    with pytest.raises(ConfigError, match="devices=4 but only 2 device"):
        device_count_for(4, 2, 4)
    with pytest.raises(ConfigError, match="seeds=3 cannot be split evenly over devices=2"):
        device_count_for(3, 2, 2)



def test_cli_exits_with_status_2_and_the_message(capsys):
    from lnnmpc.train.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["--task", "walker-fly"])
    assert exit_.value.code == 2 and "error: unknown task 'walker-fly'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--agent", "tdmpc2"])
    assert exit_.value.code == 2 and "--task is required" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:  # --set reaches make_agent(..., overrides=)
        main(["--task", "cartpole-balance", "--agent", "tdmpc2", "--small", "--set", "planner.horizon=0"])
    assert exit_.value.code == 2 and "horizon" in capsys.readouterr().err


def test_train_check_validates_and_prints_without_writing(tmp_path, capsys):
    from lnnmpc.train.cli import main

    run = tmp_path / "new" / "run"
    main(["train", "--task", "cartpole-balance", "--agent", "cfc-zp-det", "--small", "--seeds", "2", "--envs", "3",
          "--obs", "flicker=0.2,noise=0.1", "--set", "lambda_=0", "--out", str(run), "--check"])
    out = capsys.readouterr().out
    assert out.startswith(f"OK: {run} (new run)\n")
    assert "cartpole-balance, cfc-zp-det, 2 seed(s) x 3 env(s), 200,000 env steps, obs flicker0.2-noise0.1" in out
    assert "agent overrides: lambda_=0" in out
    assert "evaluation every 10,000 env steps, 10 episode(s) per seed\n" in out
    assert "chunk 987 iterations of 6 env steps (ends at 200,034 env steps)" in out
    assert not (tmp_path / "new").exists()  # nothing written
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--task", "cartpole-balance", "--small", "--set", "lamda=0", "--out", str(run), "--check"])
    assert exit_.value.code == 2 and "unknown hyperparameter 'lamda'" in capsys.readouterr().err
    main(["train", "--task", "cartpole-balance", "--small", "--eval-prior", "--out", str(run), "--check"])
    out = capsys.readouterr().out
    assert "10 episode(s) per seed, also with the policy prior alone (prior_return)\n" in out
    assert "exploration noise in training: white, drawn every step, scaled by the planner's std\n" in out
    main(["train", "--task", "cartpole-balance", "--small", "--explore-noise-beta", "1", "--set",
          "explore_min_std=0.5", "--out", str(run), "--check"])
    out = capsys.readouterr().out
    assert ("exploration noise in training: colored over each episode, spectrum 1/f^1, scaled by the planner's std "
            "(at least 0.5)\n") in out
    assert "agent overrides: explore_min_std=0.5" in out
    assert "seed phase: 5,000 env steps of uniform random actions\n" in out
    main(["train", "--task", "cartpole-balance", "--small", "--seed-noise-beta", "1", "--seed-steps", "20000",
          "--out", str(run), "--check"])
    out = capsys.readouterr().out
    assert "seed phase: 20,000 env steps of colored noise over each episode, spectrum 1/f^1, clipped\n" in out
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match="cannot be created: .*file' is not a writable folder"):
        runfolder.check_creatable(str(tmp_path / "file" / "run"))


def test_evaluation_arguments_are_checked(tmp_path):
    from lnnmpc.train.evaluate import evaluate

    with pytest.raises(ConfigError, match="unknown backend 'bullet'; known: mjx, dm_control"):
        evaluate(str(tmp_path), backend="bullet")
    with pytest.raises(ConfigError, match="episodes must be an integer >= 1, got 0"):
        evaluate(str(tmp_path), episodes=0)
    with pytest.raises(ConfigError, match="is not a run folder"):
        evaluate(str(tmp_path))


def test_first_non_finite_names_seed_iteration_and_metric():
    import numpy as np

    ok = np.zeros((2, 5))
    bad = ok.copy()
    bad[1, 3], bad[0, 4] = np.inf, np.nan
    assert first_non_finite({"reward": bad, "total_loss": ok}) is None
    assert first_non_finite({"total_loss": ok, "value_loss": bad}) == (1, 3, "value_loss")


def test_reference_lines_from_the_thesis():
    assert variant({}) == "clean" and variant({"remove_vel": True}) == "remove_vel"
    assert variant({"obs_noise": 0.2, "flicker": 0.2}) == "noise0.2-flicker0.2"
    assert references("walker-run", "tdmpc2", {"obs_noise": 0.3}) == {"thesis TD-MPC2": 387.69}
    assert references("cartpole-swingup", "cfc-op-det", {}) == {"thesis TD-MPC2": 863.9,
                                                                 "thesis CfC OP det": 880.0}
    assert references("cartpole-balance", "tdmpc2", {}) == {}


def test_new_walker_runs_of_lnn_agents_record_the_walker_defaults(tmp_path):
    """Task defaults (registry.LNN_TASK_DEFAULTS) go into a new run's overrides; the user's value wins; a run
    folder's recorded overrides hold when the same command is run again."""
    walker = {"task": "walker-run", "small": True}
    setup = validate(TrainConfig(**walker, agent="cfc-zp-det", out=str(tmp_path / "a")))
    every_lnn = {"input_transform": "symlog", "lambda_": 0.0, "rollout_steps": 3, "rollout_stride": 3,
                 "horizon": 16, "plan_horizon": 3, "learn_episode_starts": True}
    assert setup.config.overrides == {**every_lnn, "latent_head": "simnorm", "latent_size": 256}
    assert setup.loop.agent.config.model.input_transform == "symlog"
    agent = setup.loop.agent.config
    assert (agent.lambda_, agent.rollout_steps, agent.rollout_stride, agent.horizon, agent.planner.horizon,
            agent.learn_episode_starts) == (0.0, 3, 3, 16, 3, True)
    assert (agent.model.latent_head, agent.model.latent_dim) == ("simnorm", 256)
    mine = validate(TrainConfig(**walker, agent="ltc-op-det", overrides={"input_transform": "none", "lambda_": 0.5},
                                out=str(tmp_path / "b")))
    # the SimNorm head is a *-zp-det default only: an OP agent cannot carry it
    assert mine.config.overrides == {**every_lnn, "input_transform": "none", "lambda_": 0.5}
    assert (mine.loop.agent.config.lambda_, mine.loop.agent.config.model.latent_head) == (0.5, "none")
    # setting the head takes its width default with it (latent_size is refused without the head)
    headless = validate(TrainConfig(**walker, agent="ltc-zp-det", overrides={"latent_head": "none"},
                                    out=str(tmp_path / "e")))
    assert headless.config.overrides == {**every_lnn, "latent_head": "none"}
    assert headless.loop.agent.config.model.latent_dim == headless.loop.agent.config.model.hidden_size
    assert validate(TrainConfig(**walker, agent="tdmpc2", out=str(tmp_path / "c"))).config.overrides == {}
    cartpole = validate(TrainConfig(task="cartpole-swingup", small=True, agent="cfc-op-det", out=str(tmp_path / "d")))
    assert cartpole.loop.agent.config.model.input_transform == "none"
    # A run recorded before the default existed keeps its raw inputs when it is run again or resumed.
    old = str(tmp_path / "old")
    os.makedirs(old)
    runfolder.write_config(old, TrainConfig(**walker, agent="cfc-zp-det", out=old, replay_capacity=3000), {})
    again = validate(TrainConfig(**walker, agent="cfc-zp-det", out=old, overrides={"input_transform": "none"}))
    assert again.loop.agent.config.model.input_transform == "none"
    resumed = validate(resume=old).loop.agent.config
    assert (resumed.model.input_transform, resumed.lambda_, resumed.rollout_steps, resumed.rollout_stride) == (
        "none", 0.95, 1, 1)
    recorded = str(tmp_path / "recorded")
    os.makedirs(recorded)
    runfolder.write_config(recorded, TrainConfig(**walker, agent="cfc-zp-det", out=recorded, replay_capacity=3000,
                                                 overrides={"input_transform": "symlog"}), {})
    rerun = validate(TrainConfig(**walker, agent="cfc-zp-det", out=recorded))
    assert rerun.config.overrides == {"input_transform": "symlog"}


def test_the_readme_command_for_the_thesis_walker_agent_undoes_every_walker_default():
    """README: `--set input_transform=none ... --set latent_head=none` on walker gives each LNN agent exactly the
    configuration it has on a domain without task defaults (the thesis's), so no walker default is left out of
    that list."""
    from lnnmpc.agents.registry import LNN_AGENTS, make_agent, task_default_overrides

    thesis = parse_overrides(["input_transform=none", "lambda_=0.95", "rollout_steps=1", "rollout_stride=1",
                              "horizon=32", "plan_horizon=10", "learn_episode_starts=false", "latent_head=none"])
    for name in LNN_AGENTS:
        walker = make_agent(name, 24, 6, overrides=task_default_overrides(name, "walker-run", thesis)).config
        plain = make_agent(name, 24, 6, overrides=task_default_overrides(name, "cartpole-swingup")).config
        assert walker == plain, name
        defaults = make_agent(name, 24, 6, overrides=task_default_overrides(name, "walker-run")).config
        assert defaults != plain and defaults.model.input_transform == "symlog"



def test_loops_of_equal_environment_options_share_one_env():
    """build_loop takes its environments from setup.shared_env: one Env per task, physics, options and x64 mode in
    a process, so the loops of several agents or evaluations on it reuse one trace of its physics (env.py); other
    options, or float64 (whose model arrays are float64), give another Env."""
    import jax

    from lnnmpc.train.setup import build_loop, shared_env

    base = dict(task="cartpole-swingup", small=True, steps=1000, seed_steps=500)
    one = build_loop(TrainConfig(**base, agent="tdmpc2"))
    assert build_loop(TrainConfig(**base, agent="cfc-zp-det")).env is one.env is one.eval_env
    noisy = build_loop(TrainConfig(**base, agent="tdmpc2", eval_obs="noise=0.1"))
    assert noisy.env is one.env and noisy.eval_env is not one.env
    assert noisy.eval_env is shared_env("cartpole-swingup", "fast", {"obs_noise": 0.1})
    assert shared_env("cartpole-swingup", "exact", {}) is not one.env
    with jax.enable_x64(True):
        wide = shared_env("cartpole-swingup", "fast", {})
        assert wide is not one.env and wide.mjx_model.opt.timestep.dtype == np.float64
    assert shared_env("cartpole-swingup", "fast", {}) is one.env
