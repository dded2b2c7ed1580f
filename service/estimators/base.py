"""The one interface every offline estimator implements, and the trace it returns.

``socd evaluate`` runs each registered estimator on a recording through
:func:`Estimator.run`; the online service drives :class:`service.estimators.pipeline.PackEstimator`
sample by sample instead.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from service.cell.profile import CellProfile
from service.recording import Recording


@dataclass
class EstimateTrace:
    """What an estimator produced along a recording (one value per sample)."""

    soc: np.ndarray
    v_pred: np.ndarray | None = None
    soc_std: np.ndarray | None = None
    #: the filter's own SOC σ, before what it does not model is added (``soc_std`` is the published one)
    filter_soc_std: np.ndarray | None = None
    #: identified parameters over time, name -> [T] array (for plots)
    params: dict[str, np.ndarray] = field(default_factory=dict)


class Estimator(Protocol):
    """An estimator that can be scored on a recording."""

    name: str

    def run(self, recording: Recording, profile: CellProfile, soc0: float,
            history: Recording | None = None) -> EstimateTrace:
        """Estimate SOC along ``recording`` starting from the (possibly wrong) ``soc0``.

        ``history``: the recording before the start (``socd evaluate --warm-start``).  An
        estimator with polarisation states drives them with its current, as if it had been
        running; SOC is never taken from it.  Estimators without such states ignore it.
        """
        ...
