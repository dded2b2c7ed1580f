"""The two values that cross the CAN boundary, in SI units and the internal sign convention.

``PackSample`` is what the decoder hands the estimator (one per pack-current frame);
``PackSnapshot`` is what the estimator hands the encoders (CAN here, Zenoh elsewhere).
Current is positive = discharge (DESIGN §3); SOC is in [0, 1] (percent only on the wire).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.estimators.pack_view import PackView
from service.estimators.state_of_health import CellHealth

#: status flags the output DBC carries, in bit order (``SOCD_Flag<CamelCase>``)
STATUS_FLAGS: tuple[str, ...] = (
    "stale_cells",
    "checkpoint_restored",
    "ocv_init",
    "filter_reset",
    "bus_error",
    "zenoh_down",
    "publish_drops",
    "diverged",
    "param_clamped",
    "no_current",
    "counter_errors",
    "decode_errors",
    "checkpoint_corrupt",
    "clock_reanchored",
    "state_aged",
    "temperature_beyond_fit",
)


@dataclass
class PackSample:
    """One sample of the pack, clocked by a pack-current frame.

    ``voltage_v`` and ``temperature_c`` are the latest values seen for each cell (NaN where
    never seen or rejected); ``fresh[i]`` is False when cell ``i``'s voltage or temperature is
    missing, older than ``stale_after_s``, non-finite or out of range.  Estimators must not
    update a cell that is not fresh.  ``reanchored`` is True on the first sample after the
    current frame's clock jumped (the time since the previous sample is unknown).
    """

    t_s: float
    current_a: float
    voltage_v: np.ndarray
    temperature_c: np.ndarray
    fresh: np.ndarray
    reanchored: bool = False

    @property
    def n_cells(self) -> int:
        return int(self.voltage_v.size)


@dataclass
class PackSnapshot:
    """The estimator's latest answer for the whole pack (SI units, SOC in [0, 1]).

    ``params`` holds arrays ``[n_cells]`` for the keys in
    :data:`service.cell.parameters.PARAMETER_NAMES` (Zeng Fig. 1; C's are CPE coefficients,
    F·s^(α-1); missing keys are sent as 0).  ``status_flags`` uses names from
    :data:`STATUS_FLAGS` without the ``SOCD_Flag`` prefix; ``counters`` may hold
    ``frames_rejected`` and ``stale_cells`` (the latter defaults to ``stale.sum()``).
    ``pack`` is the pack view (usable SOC, energy, imbalance) or None before any estimate.
    """

    t_s: float
    soc: np.ndarray
    soc_std: np.ndarray
    voltage_v: np.ndarray
    params: dict[str, np.ndarray] = field(default_factory=dict)
    stale: np.ndarray | None = None
    status_flags: dict[str, bool] = field(default_factory=dict)
    counters: dict[str, int] = field(default_factory=dict)
    pack: PackView | None = None
    #: state of health per cell (:meth:`service.estimators.pipeline.PackEstimator.health`);
    #: None (an estimator without one): no SOCD_CellHealth frames
    health: CellHealth | None = None

    def __post_init__(self) -> None:
        if self.stale is None:
            self.stale = np.zeros(np.shape(self.soc), dtype=bool)

    @property
    def n_cells(self) -> int:
        return int(np.size(self.soc))
