"""The benchmarks' in-scan programs (``train_throughput.py --in-scan``, ``profile_update.py --what burst``) do
the same work as the calls they stand for, chained."""

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import profile_update as pu  # noqa: E402
from train_throughput import act_call, build_loop, env_step_over_seeds_and_envs, in_scan_calls  # noqa: E402

from lnnmpc.train.checkpoint import keys_as_data  # noqa: E402


def assert_trees_close(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(keys_as_data(a)), jax.tree_util.tree_leaves(keys_as_data(b)),
                    strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)


def test_in_scan_act_and_env_steps_equal_the_chained_calls():
    loop = build_loop("cartpole-balance", "tdmpc2", 2, True, {})
    ts = jax.jit(jax.vmap(loop.init))(jax.random.split(jax.random.key(0), 1))  # no replay needed here
    n = 3
    calls = in_scan_calls(loop, ts, n)
    act_fn, (agent, carry, obs, dt, keys) = calls["act"]
    final_carry, actions = act_fn(agent, carry, obs, dt, keys)
    assert actions.shape == (n, 1, 2, loop.env.action_size)
    one = act_call(loop.agent, ts)[0]  # the standalone act call the scan stands for
    for i in range(n):
        action, carry = one(agent, carry, obs, dt, keys[i])
        np.testing.assert_allclose(np.asarray(action), np.asarray(actions[i]), rtol=1e-5, atol=1e-6)
    assert_trees_close(final_carry, carry)

    env_fn, (env, zeros, env_keys) = calls["env"]
    step = jax.jit(env_step_over_seeds_and_envs(loop))
    by_hand = env
    for i in range(n):
        by_hand = step(by_hand, zeros, env_keys[i])
    assert_trees_close(env_fn(env, zeros, env_keys), by_hand)
    assert int(np.asarray(by_hand.t).max()) > int(np.asarray(env.t).max())  # the steps did advance
    # as in the training chunk, a finished environment restarts (Env.step_or_reset) instead of stepping on
    finished = env.replace(done=env.done.at[0, 0].set(True), t=env.t.at[0, 0].set(7))
    restarted = step(finished, zeros, env_keys[0])
    assert int(restarted.t[0, 0]) == 0 and int(restarted.t[0, 1]) == int(env.t[0, 1]) + 1
    # calls["update"] is TrainingLoop.update_burst itself (tests/test_loop*.py), so it is not re-run here.


def test_profile_call_reports_figures_per_unit_of_a_burst():
    fn = jax.jit(lambda x: jax.lax.scan(lambda c, _: (jnp.tanh(c @ c), None), x, None, length=4)[0])
    summary = pu.profile_call(fn, (jnp.ones((16, 16)),), calls=2, warmup=1, top=3, per_call=4)
    assert summary["calls"] == 8
    assert summary["kernels_per_call"] > 0 and summary["wall_ms_per_call"] > 0


def test_chunk_only_refuses_the_flags_that_time_other_parts(capsys):
    import pytest
    import train_throughput

    for flags in (["--update-only"], ["--skip-chunk"], ["--in-scan", "4"]):
        with pytest.raises(SystemExit):
            train_throughput.main(["--small", "--chunk-only", *flags, "--out", os.devnull])
        assert "--chunk-only times the chunk alone" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train_throughput.main(["--small", "--chunk-only", "--chunk", "0", "--out", os.devnull])
    assert "--chunk must be >= 1 iteration, got 0" in capsys.readouterr().err


def test_benchmark_loop_takes_the_batch_size_and_update_kernels_refuses_a_bad_one(capsys, monkeypatch):
    import pytest
    import update_kernels

    from lnnmpc.replay import replay_sample

    loop = build_loop("cartpole-balance", "tdmpc2", 1, True, {}, batch_size=8)
    assert loop.config.batch_size == 8
    ts = jax.eval_shape(loop.init, jax.random.key(0))
    sample = lambda replay, key: replay_sample(replay, key, loop.config.batch_size, loop.agent.sequence_length)
    records, _, _ = jax.eval_shape(sample, ts.replay, jax.random.key(1))
    assert {leaf.shape[1] for leaf in jax.tree_util.tree_leaves(records)} == {8}  # (sequence, B, ...)
    monkeypatch.setattr(sys, "argv", ["update_kernels.py", "--loop-seeds", "1", "--batch-size", "0"])
    with pytest.raises(SystemExit):
        update_kernels.main()
    assert "--batch-size must be >= 1, got 0" in capsys.readouterr().err
