"""benchmarks/summarize.py names what each benchmark record changed from the defaults, and renders the profile and
update-only records it did not know before."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import summarize  # noqa: E402

WALKER_DEFAULTS = ["input_transform=symlog", "lambda_=0", "rollout_steps=3", "rollout_stride=3", "horizon=16",
                   "plan_horizon=3", "learn_episode_starts=true", "latent_head=simnorm", "latent_size=256"]
HEAD = "no latent_head=simnorm; no latent_size=256"


def payload(overrides, flags="", precision="default", benchmark="train_throughput", results=None):
    return {"benchmark": benchmark, "env": {"device": "GPU X", "xla_flags": flags},
            "args": {"matmul_precision": precision, "overrides": overrides, "task": "walker-run",
                     "agent": "cfc-zp-det", "seeds": 3},
            "results": results or []}


def test_setting_hides_only_the_agents_own_task_defaults():
    walker = payload([*WALKER_DEFAULTS, "scan_unroll=4"])
    assert summarize._setting(walker, "walker-run", "cfc-zp-det") == " (scan_unroll=4)"
    # the same overrides are no defaults on cartpole, nor for tdmpc2 on walker
    assert summarize._setting(walker, "cartpole-swingup", "cfc-zp-det") == (
        f" ({'; '.join(WALKER_DEFAULTS)}; scan_unroll=4)")
    assert "lambda_=0" in summarize._setting(walker, "walker-run", "tdmpc2")
    # the SimNorm head is a *-zp-det default only: for an OP agent it is a change
    assert summarize._setting(walker, "walker-run", "cfc-op-det") == (
        " (latent_head=simnorm; latent_size=256; scan_unroll=4)")
    # a walker default set to another value is a change
    assert summarize._setting(payload([*WALKER_DEFAULTS[:3], "lambda_=0.95", *WALKER_DEFAULTS[4:]][1:]),
                              "walker-run", "cfc-zp-det") == (
        " (lambda_=0.95; no input_transform=symlog; no rollout_stride=3)")
    # a record made before a default existed ran without it (the benchmarks apply --set only), and says so
    before_stride = payload(WALKER_DEFAULTS[:3])
    assert summarize._setting(before_stride, "walker-run", "cfc-zp-det") == (
        " (no rollout_stride=3; no horizon=16; no plan_horizon=3; no learn_episode_starts=True; " + HEAD + ")")
    before_head = payload(WALKER_DEFAULTS[:7])
    assert summarize._setting(before_head, "walker-run", "cfc-zp-det") == f" ({HEAD})"
    assert summarize._setting(before_head, "walker-run", "ltc-zp-stoch") == ""
    assert summarize._setting(payload([]), "walker-run", "tdmpc2") == ""
    both = payload(WALKER_DEFAULTS, flags="--xla_gpu_enable_command_buffer=", precision="bfloat16")
    assert summarize._setting(both, "walker-run", "cfc-zp-det") == (
        " (bfloat16 products; XLA_FLAGS `--xla_gpu_enable_command_buffer=`)")
    assert summarize._setting(payload(WALKER_DEFAULTS), "walker-run", "cfc-zp-det") == ""


def test_update_only_and_profile_records_are_tabulated(tmp_path, monkeypatch, capsys):
    update_only = payload([*WALKER_DEFAULTS, "scan_unroll=43"], results=[
        {"task": "walker-run", "agent": "cfc-zp-det", "seeds": 3, "envs": 1, "update_ms": 12.87,
         "update_compile_s": 70.0}])
    category = {"kernels_per_call": 239.0, "ms_per_call": 3.5}
    profile = payload(WALKER_DEFAULTS, benchmark="profile_update", results={"update": {
        "wall_ms_per_call": 14.21, "busy_ms_per_call": 10.33, "busy_fraction": 0.727, "kernels_per_call": 1383.0,
        "by_category": {"matmul": category, "other": {"kernels_per_call": 0.2, "ms_per_call": 0.001}}},
        "burst": {"wall_ms_per_call": 11.11, "busy_ms_per_call": 10.4, "busy_fraction": 0.94,
                  "kernels_per_call": 1107.0, "by_category": {"matmul": category},
                  "by_scope": {"td_targets forward": {"kernels_per_call": 26.0, "ms_per_call": 0.41},
                               "model_losses backward": {"kernels_per_call": 130.0, "ms_per_call": 3.99}}}})
    for name, data in (("a-update-only.json", update_only), ("b-profile.json", profile)):
        (tmp_path / name).write_text(json.dumps(data))
    monkeypatch.setattr(summarize, "RESULTS", str(tmp_path))
    monkeypatch.setattr(summarize, "plot_env_throughput", lambda path: None)
    summarize.main()
    out = capsys.readouterr().out
    assert ("| walker-run | cfc-zp-det (scan_unroll=43) | 3 | 1 | — | — | 12.87 | — | — | GPU X | "
            "a-update-only.json |") in out
    assert ("| walker-run | cfc-zp-det | 3 | update | 14.21 | 10.33 | 0.73 | 1383 | matmul 239 / 3.50 ms | — | GPU X | "
            "b-profile.json |") in out
    # the named scopes, the largest first
    assert ("| burst | 11.11 | 10.40 | 0.94 | 1107 | matmul 239 / 3.50 ms | model_losses backward 3.99 ms, "
            "td_targets forward 0.41 ms | GPU X |") in out


def test_in_scan_times_follow_the_standalone_ones():
    record = {"act_ms": 2.5, "env_ms": 1.21, "update_ms": 84.26, "update_in_scan_ms": 42.0}
    assert summarize._with_in_scan(record, "update") == "84.26 (42.00)"
    assert summarize._with_in_scan(record, "env") == "1.21"
    assert summarize._with_in_scan({"update_ms": 12.0}, "act") == "—"
