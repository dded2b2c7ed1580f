"""Coulomb counting: the baseline every model-based estimator must beat.

    SOC_k = SOC_{k-1} - I_k dt_k / (3600 Q)

(Zeng Eq. 4 with the sample period and 3600 s/h restored; backward zero-order hold:
the current of row ``k`` flowed over ``(t_{k-1}, t_k]``, first sample ``dt = 0``.)
``Q`` is the profile capacity times its ``capacity_scale`` extension.  Nothing else
of the profile is used: no current-bias correction, no clipping, no voltage — an
error in ``soc0`` or in the current sensor stays in the estimate for good.
"""

from __future__ import annotations

from service.cell.coulomb import coulomb_soc
from service.cell.profile import CellProfile
from service.estimators.base import EstimateTrace
from service.recording import Recording


class CoulombCounter:
    """Pure coulomb counting from ``soc0`` (name ``"coulomb"``); no voltage, no v_pred."""

    name = "coulomb"

    def run(self, recording: Recording, profile: CellProfile, soc0: float,
            history: Recording | None = None) -> EstimateTrace:
        """``history`` is ignored: coulomb counting has no state but SOC."""
        capacity = profile.effective_capacity_ah
        soc = coulomb_soc(recording.time_s, recording.current_a, capacity, soc0)
        return EstimateTrace(soc=soc, v_pred=None, soc_std=None, params={})
