"""State of health per cell, as the pack estimator reports it (issue 28).

:meth:`service.estimators.pipeline.PackEstimator.health` builds it; the daemon copies it into
each snapshot, the CAN encoder (``SOCD_CellHealth``) and the Zenoh parameter payloads
(``CellParams`` schema 2) read its fields by name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CellHealth:
    """Arrays ``[N]``, one value per cell.

    ``capacity_ah`` and its 1-σ ``capacity_std_ah`` (the profile's capacity with σ 0 when the
    online estimate is frozen); ``capacity_rel`` = capacity / the profile's (SOH-energy);
    ``resistance_rel`` = (R_ohm + R_ct) / the profile's at the cell's temperature and SOC
    (SOH-power)."""

    capacity_ah: np.ndarray
    capacity_std_ah: np.ndarray
    capacity_rel: np.ndarray
    resistance_rel: np.ndarray

    @property
    def capacity_std_rel(self) -> np.ndarray:
        """σ of ``capacity_rel``: ``capacity_std_ah`` relative to the profile's capacity."""
        return self.capacity_std_ah * self.capacity_rel / self.capacity_ah

    def copy(self) -> CellHealth:
        """The same figures in float arrays of its own (a snapshot must not change under a reader)."""
        return CellHealth(*(np.array(a, dtype=float) for a in
                            (self.capacity_ah, self.capacity_std_ah, self.capacity_rel, self.resistance_rel)))
