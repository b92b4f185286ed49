"""Published final returns to draw next to a learning curve: the thesis's Tables 5.3–5.6.

Values are the mean evaluation returns (10 episodes) the thesis reports at the end of training (at most 200K
environment steps; runs that converged early were stopped earlier). The thesis's "cartpole" is
cartpole-swingup and "cartpole-sparse" cartpole-swingup-sparse. Its perturbed cartpole variants train and
evaluate with sensor noise σ and flickering (s = 0.2 in this project, SPEC §3); the acrobot and walker variants
with noise only. Numbers of TD-MPC2's paper are not included (the project does not ship its result files).
"""

from __future__ import annotations

from collections.abc import Mapping

AGENT_LABELS = {"tdmpc2": "TD-MPC2", "cfc-zp-det": "CfC ZP det", "cfc-op-det": "CfC OP det",
                "cfc-op-stoch": "CfC OP stoch", "ltc-zp-det": "LTC ZP det", "ltc-op-det": "LTC OP det",
                "ltc-op-stoch": "LTC OP stoch"}
_ORDER = ("tdmpc2", "cfc-zp-det", "cfc-op-det", "cfc-op-stoch", "ltc-zp-det", "ltc-op-det", "ltc-op-stoch")


def _row(*values: float) -> dict[str, float]:
    return dict(zip(_ORDER, values, strict=True))


# (task, variant) -> {agent: final mean return}; variant names an evaluation corruption setting.
THESIS = {
    ("cartpole-swingup", "clean"): _row(863.9, 856.0, 880.0, 856.0, 822.04, 860.0, 824.35),
    ("cartpole-swingup-sparse", "clean"): _row(784.8, 769.4, 799.5, 805.90, 768.40, 726.85, 752.40),
    ("acrobot-swingup", "clean"): _row(329.0, 883.1, 544.7, 263.26, 769.29, 284.80, 536.36),
    ("walker-run", "clean"): _row(830.9, 785.98, 632.7, 724.32, 767.53, 653.81, 633.60),
    ("cartpole-swingup", "remove_vel"): _row(193.22, 603.0, 868.27, 705.80, 726.85, 846.07, 724.50),
    ("cartpole-swingup", "noise0.1-flicker0.2"): _row(378.82, 798.89, 878.0, 825.0, 780.85, 824.35, 804.30),
    ("cartpole-swingup", "noise0.2-flicker0.2"): _row(353.63, 742.19, 756.0, 693.08, 736.24, 744.14, 763.06),
    ("cartpole-swingup", "noise0.3-flicker0.2"): _row(365.71, 550.69, 645.49, 600.22, 677.99, 471.47, 721.52),
    ("acrobot-swingup", "noise0.1"): _row(90.50, 559.78, 564.55, 272.56, 468.84, 326.23, 263.19),
    ("acrobot-swingup", "noise0.2"): _row(57.74, 448.90, 495.90, 285.83, 370.50, 307.21, 254.91),
    ("acrobot-swingup", "noise0.3"): _row(74.80, 322.62, 374.15, 239.59, 281.79, 224.97, 201.62),
    ("walker-run", "noise0.1"): _row(581.92, 764.30, 589.87, 697.32, 714.06, 570.15, 642.81),
    ("walker-run", "noise0.2"): _row(495.75, 734.35, 569.53, 672.14, 607.04, 454.38, 597.67),
    ("walker-run", "noise0.3"): _row(387.69, 647.65, 519.73, 630.33, 546.43, 501.66, 485.32),
}


def variant(options: Mapping) -> str:
    """The table variant of evaluation corruption options (``clean``, ``remove_vel``, ``noise0.1-flicker0.2``)."""
    if options.get("remove_vel") and not any(options.get(k) for k in ("obs_noise", "flicker", "delay")):
        return "remove_vel"
    parts = [f"{name}{options[key]:g}" for key, name in (("obs_noise", "noise"), ("flicker", "flicker"),
                                                         ("delay", "delay")) if options.get(key)]
    return "-".join(parts) if parts and not options.get("remove_vel") else ("clean" if not parts else "other")


def references(task: str, agent: str, eval_options: Mapping) -> dict[str, float]:
    """Reference lines for a run: the thesis's TD-MPC2 and the same agent, where the thesis has them."""
    row = THESIS.get((task, variant(eval_options)), {})
    return {f"thesis {AGENT_LABELS[name]}": row[name] for name in dict.fromkeys(("tdmpc2", agent)) if name in row}
