"""Liquid recurrent cells (CfC, LTC) with ncps-torch semantics, a scan-based unroll and an ncps weight loader.

``CfCCell`` / ``LTCCell`` are ``flax.linen`` modules called as ``cell.apply(variables, state, x, dt)``
and returning ``(new_state, output)``; ``unroll`` runs one over a time-major sequence with per-sample Δt
and episode resets; ``load_ncps_state_dict`` converts ncps 1.0.1 torch weights into ``variables``.
"""

from lnnmpc.nets.cfc import BACKBONE_ACTIVATIONS, CFC_MODES, CfCCell, lecun_tanh
from lnnmpc.nets.ltc import LTC_MAPPINGS, LTCCell, clip_ltc_parameters, fully_connected_polarities
from lnnmpc.nets.ncps_loader import load_ncps_state_dict
from lnnmpc.nets.unroll import UnrollResult, scan_steps, time_deltas_for_sequence, unroll

__all__ = [
    "BACKBONE_ACTIVATIONS",
    "CFC_MODES",
    "LTC_MAPPINGS",
    "CfCCell",
    "LTCCell",
    "UnrollResult",
    "clip_ltc_parameters",
    "fully_connected_polarities",
    "lecun_tanh",
    "load_ncps_state_dict",
    "scan_steps",
    "time_deltas_for_sequence",
    "unroll",
]
