"""The thesis's numbers (chapter 5) that our studies are compared with, with the table each comes from.

``THESIS[(task, eval_obs, agent)] = Reference(mean, std, source)``: the mean return over 10 evaluation episodes
and its standard deviation (None where the thesis prints none) after at most 200K environment steps. ``eval_obs``
is the canonical corruption tag of the evaluation setting (:func:`eval_key`, e.g. ``clean``, ``novel`` for
``remove_vel``, ``flicker0.2-noise0.3``). The thesis's "cartpole" is cartpole-swingup and "cartpole-sparse"
cartpole-swingup-sparse; its perturbed cartpole variants are trained at σ = 0.1 with flickering s = 0.2 and
evaluated at σ with the same flickering; acrobot and walker variants use noise only.

The TD-MPC2 row of Table 5.3 is, as the thesis states (§5.5), TD-MPC2's published result at 200K steps (the
authors' result files); in Tables 5.4–5.6 it is the thesis's own TD-MPC2 run (TD-MPC2 publishes no noisy
variants). Figures 5.18 and 5.19 print no numbers in the text, so they have no entries here.
"""

from __future__ import annotations

import dataclasses

from lnnmpc.train.config import obs_tag, parse_obs

AGENT_ORDER = ("tdmpc2", "cfc-zp-det", "cfc-op-det", "cfc-op-stoch", "ltc-zp-det", "ltc-op-det", "ltc-op-stoch")


@dataclasses.dataclass(frozen=True)
class Reference:
    """A thesis value: mean return, its std (None: not printed) and the table it comes from."""

    mean: float
    std: float | None
    source: str

    def text(self) -> str:
        return f"{self.mean:.1f}" if self.std is None else f"{self.mean:.1f} ± {self.std:.1f}"


def eval_key(obs: str | dict) -> str:
    """Canonical tag of an evaluation corruption (text like ``"noise=0.1,flicker=0.2"`` or make() options)."""
    return obs_tag(parse_obs(obs))


def _table(source: str, task: str, obs: str, values: tuple) -> dict:
    """{(task, tag, agent): Reference} for one column of a thesis table; ``values`` in AGENT_ORDER, each a mean
    or a (mean, std) pair."""
    rows = {}
    for agent, value in zip(AGENT_ORDER, values, strict=True):
        mean, std = value if isinstance(value, tuple) else (value, None)
        rows[task, eval_key(obs), agent] = Reference(float(mean), None if std is None else float(std), source)
    return rows


_NOISY_CARTPOLE = "flicker=0.2,noise={}"
THESIS: dict[tuple[str, str, str], Reference] = {
    **_table("Table 5.3", "cartpole-swingup", "", (863.9, 856.0, (880.0, 6.7), (856.0, 7.4), (822.04, 0.90),
                                                   (860.0, 9.04), (824.35, 12.08))),
    **_table("Table 5.3", "cartpole-swingup-sparse", "", (784.8, (769.4, 0.92), (799.5, 3.14), (805.90, 5.20),
                                                          (768.40, 0.97), (726.85, 82.04), (752.40, 23.98))),
    **_table("Table 5.3", "acrobot-swingup", "", (329.0, (883.1, 0.2), (544.7, 6.73), (263.26, 61.96),
                                                  (769.29, 0.62), (284.80, 102.12), (536.36, 2.54))),
    **_table("Table 5.3", "walker-run", "", (830.9, (785.98, 16.14), (632.7, 34.12), (724.32, 16.03),
                                             (767.53, 24.48), (653.81, 13.59), (633.60, 40.63))),
    **_table("Table 5.4", "cartpole-swingup", "remove_vel=1", ((193.22, 13.68), 603.0, (868.27, 2.12),
                                                               (705.80, 103.31), (726.85, 82.04), (846.07, 2.65),
                                                               (724.50, 63.09))),
    **_table("Table 5.4", "cartpole-swingup", _NOISY_CARTPOLE.format(0.1), (
        (378.82, 45.43), (798.89, 50.64), (878.0, 34.07), (825.0, 25.45), (780.85, 29.36), (824.35, 16.02),
        (804.30, 54.22))),
    **_table("Table 5.4", "cartpole-swingup", _NOISY_CARTPOLE.format(0.2), (
        (353.63, 76.27), (742.19, 52.02), (756.0, 70.0), (693.08, 54.02), (736.24, 74.14), (744.14, 36.91),
        (763.06, 55.91))),
    **_table("Table 5.4", "cartpole-swingup", _NOISY_CARTPOLE.format(0.3), (
        (365.71, 47.37), (550.69, 76.55), (645.49, 92.07), (600.22, 79.86), (677.99, 52.82), (471.47, 104.39),
        (721.52, 78.38))),
    **_table("Table 5.5", "acrobot-swingup", "noise=0.1", (
        (90.50, 104.67), (559.78, 28.61), (564.55, 35.14), (272.56, 93.26), (468.84, 44.98), (326.23, 72.63),
        (263.19, 71.27))),
    **_table("Table 5.5", "acrobot-swingup", "noise=0.2", (
        (57.74, 55.10), (448.90, 75.03), (495.90, 48.82), (285.83, 56.31), (370.50, 51.94), (307.21, 76.20),
        (254.91, 111.96))),
    **_table("Table 5.5", "acrobot-swingup", "noise=0.3", (
        (74.80, 41.12), (322.62, 113.33), (374.15, 47.69), (239.59, 161.22), (281.79, 64.72), (224.97, 121.64),
        (201.62, 95.31))),
    **_table("Table 5.6", "walker-run", "noise=0.1", (
        (581.92, 37.27), (764.30, 15.06), (589.87, 20.48), (697.32, 17.28), (714.06, 11.12), (570.15, 20.48),
        (642.81, 17.38))),
    **_table("Table 5.6", "walker-run", "noise=0.2", (
        (495.75, 38.88), (734.35, 22.53), (569.53, 36.58), (672.14, 12.43), (607.04, 19.83), (454.38, 49.65),
        (597.67, 32.84))),
    **_table("Table 5.6", "walker-run", "noise=0.3", (
        (387.69, 38.61), (647.65, 38.56), (519.73, 26.55), (630.33, 27.61), (546.43, 47.25), (501.66, 39.56),
        (485.32, 64.43))),
}


def thesis_value(task: str, eval_obs: str | dict, agent: str) -> Reference | None:
    """The thesis's value for ``agent`` on ``task`` evaluated under ``eval_obs``, or None if it has none."""
    return THESIS.get((task, eval_key(eval_obs), agent))


def tdmpc2_value(task: str, eval_obs: str | dict) -> Reference | None:
    """The TD-MPC2 entry of the same thesis table (published result in Table 5.3; the thesis's run elsewhere)."""
    return thesis_value(task, eval_obs, "tdmpc2")
