"""Resuming a run folder: an incompatible configuration or changed agent hyperparameters are refused before
anything compiles, fields unused or added since are ignored, committed GPU runs read as today's configuration,
and one process at a time trains in a folder."""

from __future__ import annotations

import dataclasses
import os

import pytest

from lnnmpc.train import runfolder
from lnnmpc.train.config import ConfigError, TrainConfig, incompatibilities
from lnnmpc.train.setup import validate


def test_resuming_with_an_incompatible_configuration_is_refused(tmp_path):
    run = str(tmp_path / "run")
    os.makedirs(run)
    saved = TrainConfig(task="cartpole-balance", small=True, out=run, replay_capacity=3000)
    runfolder.write_config(run, saved, {})
    changed = TrainConfig(task="cartpole-balance", small=True, out=run, seed=3, eval_obs="noise=0.3", steps=10**6)
    assert incompatibilities(saved, dataclasses.replace(changed, replay_capacity=3000)) == [
        "eval_obs: checkpoint has {}, now {'obs_noise': 0.3}", "seed: checkpoint has 0, now 3"]
    with pytest.raises(ConfigError) as error:
        validate(changed)
    assert "cannot resume" in str(error.value) and "seed: checkpoint has 0, now 3" in str(error.value)
    assert ("Only steps, name, runs_dir, checkpoint_every, keep_checkpoints, devices, tensorboard, wandb, "
            "compile_cache, compile_ahead, eval_prior, eval_policies, deterministic and overrides that keep"
            ) in str(error.value)
    # steps, checkpoint cadence, devices and the like may change; the replay buffer keeps its size.
    setup = validate(resume=run, steps=10**6)
    assert setup.config.steps == 10**6 and setup.config.replay_capacity == 3000 and setup.resume_step is None
    # the extended budget sizes the chunks: the run ends within one iteration per chunk past 10**6
    chunks = -(-(10**6 // setup.per_iteration) // setup.chunk)
    assert 10**6 <= setup.final_env_steps < 10**6 + chunks * setup.per_iteration
    assert TrainConfig.from_dict(saved.to_dict()) == saved
    # the prior's evaluations may be turned on for the rest of a run: they change nothing of the training
    assert incompatibilities(saved, dataclasses.replace(saved, eval_prior=True)) == []
    with pytest.raises(ConfigError, match=r"unknown configuration key\(s\) \['colour'\]"):
        TrainConfig.from_dict({**saved.to_dict(), "colour": 1})


def test_resuming_with_changed_agent_hyperparameters_is_refused(tmp_path):
    from lnnmpc.train.compat import agent_config_json, check_agent_config
    from lnnmpc.train.setup import build_loop

    run = str(tmp_path)
    agent = build_loop(TrainConfig(task="cartpole-balance", small=True, model_size=1)).agent.config
    saved = agent_config_json(agent)
    saved["planner"]["horizon"] = 7
    runfolder.write_config(run, TrainConfig(task="cartpole-balance", out=run), {"agent_config": saved})
    with pytest.raises(ConfigError) as error:
        check_agent_config(run, agent)
    assert "planner.horizon: checkpoint has 7, now 3" in str(error.value)
    assert "Restore them with --set planner.horizon=7 or start a new run" in str(error.value)
    runfolder.write_config(run, TrainConfig(task="cartpole-balance", out=run),
                           {"agent_config": agent_config_json(agent)})
    check_agent_config(run, agent)  # equal hyperparameters: no error


def test_resume_check_ignores_unused_fields_and_knows_fields_added_since(tmp_path):
    """A checkpoint from before nll_beta, joint_grad_clip, flat_optimizer and rollout_steps existed and with the
    old free-bits default: a det variant resumes with the old per-group clipping and per-leaf Adam (it uses neither
    NLL field); an OP-stoch run is refused with the exact --set flags, and resumes once they are given."""
    from lnnmpc.agents.registry import make_agent
    from lnnmpc.train.compat import agent_config_json, check_agent_config

    run = str(tmp_path)

    def saved_like(agent_config):
        old = agent_config_json(agent_config)
        del old["nll_beta"], old["joint_grad_clip"], old["flat_optimizer"], old["rollout_steps"]  # did not exist
        old["free_bits"] = -1.0
        runfolder.write_config(run, TrainConfig(task="cartpole-balance", out=run), {"agent_config": old})

    det = make_agent("cfc-op-det", 5, 1).config
    saved_like(det)
    with pytest.raises(ConfigError, match="Restore them with --set flat_optimizer=False --set joint_grad_clip=False "
                                          "or start a new run"):
        check_agent_config(run, det)
    old_clip = {"joint_grad_clip": "false", "flat_optimizer": "false"}
    check_agent_config(run, make_agent("cfc-op-det", 5, 1, overrides=old_clip).config)
    stoch = make_agent("cfc-op-stoch", 5, 1, overrides=old_clip).config
    saved_like(stoch)
    with pytest.raises(ConfigError) as error:
        check_agent_config(run, stoch)
    message = str(error.value)
    assert "free_bits: checkpoint has -1.0, now -2.0" in message and "nll_beta: checkpoint has 0.0, now 1.0" in message
    assert "Restore them with --set free_bits=-1.0 --set nll_beta=0.0" in message
    check_agent_config(run, make_agent("cfc-op-stoch", 5, 1, overrides={
        "free_bits": "-1.0", "nll_beta": "0.0", **old_clip}).config)
    zp = make_agent("cfc-zp-stoch", 5, 1, overrides={"nll_beta": 0, **old_clip}).config
    saved_like(zp)
    check_agent_config(run, zp)  # ZP does not use free bits
    with pytest.raises(ConfigError, match="rollout_steps: checkpoint has 1, now 3"):  # older runs: the thesis's 1
        check_agent_config(run, make_agent("cfc-zp-stoch", 5, 1, overrides={
            "nll_beta": 0, "rollout_steps": 3, **old_clip}).config)
    # A TD-MPC2 checkpoint from before the SimNorm LayerNorm and the joint clip: its layout and clipping restored.
    old = agent_config_json(make_agent("tdmpc2", 5, 1).config)
    del old["joint_grad_clip"], old["model"]["simnorm_layer_norm"], old["flat_optimizer"]
    runfolder.write_config(run, TrainConfig(task="cartpole-balance", out=run), {"agent_config": old})
    with pytest.raises(ConfigError, match="Restore them with --set flat_optimizer=False --set joint_grad_clip=False "
                                          "--set model.simnorm_layer_norm=False or start a new run"):
        check_agent_config(run, make_agent("tdmpc2", 5, 1).config)
    check_agent_config(run, make_agent("tdmpc2", 5, 1, overrides={
        **old_clip, "model.simnorm_layer_norm": "false"}).config)
    # A liquid run from before the latent head (and its width and group size) existed resumes as it was; a head
    # run from before latent_size resumes with the head's latent as wide as the cell's state (latent_size 0).
    for overrides, missing in (({}, ("latent_head", "simnorm_dim", "latent_size", "latent_obs_skip",
                                     "latent_head_hidden")),
                               ({"model.latent_head": "simnorm"}, ("latent_size", "latent_obs_skip",
                                                                   "latent_head_hidden"))):
        agent = make_agent("cfc-zp-det", 5, 1, overrides=overrides).config
        old = agent_config_json(agent)
        for name in missing:
            del old["model"][name]
        runfolder.write_config(run, TrainConfig(task="cartpole-balance", out=run), {"agent_config": old})
        check_agent_config(run, agent)
    with pytest.raises(ConfigError, match="model.latent_size: checkpoint has 0, now 16"):
        check_agent_config(run, make_agent("cfc-zp-det", 5, 1, overrides={"model.latent_head": "simnorm",
                                                                           "model.latent_size": 16}).config)



def test_a_run_folder_trains_in_one_process_at_a_time(tmp_path):
    """runfolder.hold_run: while one process holds a run folder (a run finishing its chunk and checkpoint after
    SIGTERM), training in it from another process is refused before compiling, naming the folder and the holder's
    pid; the lock goes with the holder."""
    import subprocess
    import sys

    import lnnmpc

    run = str(tmp_path / "run")
    os.makedirs(run)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys; from lnnmpc.train import runfolder; "
         f"lock = runfolder.hold_run({run!r}); print('held', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        config = TrainConfig(task="cartpole-balance", small=True, out=run, steps=200, seed_steps=100)
        with pytest.raises(ConfigError, match=f"run folder '{run}' is in use by another training process "
                                              rf"\(pid {holder.pid}\)"):
            lnnmpc.train(config)
        assert not os.path.exists(os.path.join(run, runfolder.CONFIG_FILE))  # nothing written
    finally:
        holder.communicate("")  # the holder exits: its lock goes with it
    with runfolder.hold_run(run) as lock:
        assert open(os.path.join(run, runfolder.LOCK_FILE)).read() == f"{os.getpid()}\n"
        with pytest.raises(ConfigError, match=rf"in use by another training process \(pid {os.getpid()}\)"):
            runfolder.hold_run(run)  # a second open of the lock conflicts even within one process
    assert lock.closed
    runfolder.hold_run(run).close()


def test_a_committed_run_from_before_the_newest_agent_fields_reads_as_the_same_configuration():
    """A GPU run folder filed under experiments/results before the agent's newest fields existed
    (``learn_episode_starts``) compares equal to its configuration built by today's code: every field added
    since holds its old behaviour's value in ``ADDED_AGENT_FIELDS``, so such a run still resumes and pools
    (``tables --pool``) with new runs of the same configuration."""
    import json
    import os

    from lnnmpc.agents.registry import make_agent
    from lnnmpc.train.compat import agent_config_changes, agent_config_json

    run = os.path.join(os.path.dirname(__file__), "..", "experiments", "results",
                       "cfc-walker-simnorm-latent512-200k-h200", "walker-simnorm-latent512-seed1")
    with open(os.path.join(run, "config.json")) as f:
        saved = json.load(f)
    assert "learn_episode_starts" not in saved["agent_config"]  # the run predates it
    assert "eval_prior" not in saved["config"]  # and the prior's evaluations: off, as it ran
    config = TrainConfig.from_dict(saved["config"])
    assert config.eval_prior is False
    agent = make_agent(config.agent, 24, 6, model_size=config.model_size, small=config.small,
                       overrides=config.overrides or None).config
    assert agent_config_changes(saved["agent_config"], agent_config_json(agent), agent.inactive_fields()) == []
    new = make_agent(config.agent, 24, 6, overrides={**config.overrides, "learn_episode_starts": True}).config
    assert agent_config_changes(saved["agent_config"], agent_config_json(new), new.inactive_fields()) == [
        ("learn_episode_starts", False, True)]
