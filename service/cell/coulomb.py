"""Coulomb counting (Zeng Eq. 4 with the sample period and the seconds per hour restored).

    SOC_k = SOC_{k-1} - I_k dt_k / (3600 Q)

Backward zero-order hold: the current of row ``k`` flowed over ``(t_{k-1}, t_k]``, so the
first sample moves nothing.  Current positive = discharge (DESIGN §3).
"""

from __future__ import annotations

import numpy as np

from service.cell.units import SECONDS_PER_HOUR


def coulomb_soc(time_s: np.ndarray, current_a: np.ndarray, capacity_ah: float, soc0: float) -> np.ndarray:
    """SOC counted from ``soc0`` at ``time_s[0]``; row k's current flowed over (t_{k-1}, t_k]."""
    dq = np.concatenate([[0.0], current_a[1:] * np.diff(time_s)]) / SECONDS_PER_HOUR
    return soc0 - np.cumsum(dq) / capacity_ah
