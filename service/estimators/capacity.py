"""Online capacity of every cell: a dual EKF beside the SOC filter (Plett 2004, Part 3, §4).

The papers run the SOC filter with the capacity given (Zeng Eq. 4).  A cell whose capacity
differs from the profile's drifts: the SOC filter integrates ``I·dt / Q_profile`` and its
voltage correction is too weak to hold the drift (its SOC σ settles at 0.05 % while the
error reaches 3 %).  This estimator learns ``φ = Q_nominal / Q`` per cell (inverse relative
capacity: SOC moves linearly in it) as a scalar EKF whose measurement is the SOC filter's
own voltage innovation, with the total-derivative Jacobian through the filter's gain (the
same recursion as the fast identifier's, Zeng Table 1 / Plett's dual EKF):

    s⁻_k = s⁺_{k-1} - I_k Δt / (3600 Q_nominal)        (dSOC⁻/dφ, Zeng Eq. 4)
    H_k  = dOCV/dSOC · s⁻_k                            (dV/dφ)
    K    = P H / (H² P + κ σ²_e),  φ += K e,  P -= K H P
    s⁺_k = (1 - K_soc dOCV/dSOC) s⁻_k

with ``e``/``σ²_e`` the SOC filter's innovation and its variance, and ``κ``
(``capacity_innovation_inflation``) the number of consecutive innovations that carry
about one independent sample: model error makes them correlated over tens of seconds.
A correction ``δφ`` also moves the SOC by ``s⁺ δφ`` (what the filter would hold had it
counted with the new capacity all along; without it the old SOC error lingers), and
``φ``'s variance enters the SOC filter's process noise as ``(I Δt / 3600 Q_nom)² P``,
so the SOC σ includes what the capacity is not sure of.

``mode``:

- ``"pack-relative"`` (default): the innovation of each cell minus the pack's median
  innovation.  Cells of one pack share the profile, and the profile's model error is
  common to them: along a discharge it moves the voltage as a capacity error would
  (``research.capacity_bias`` measures it band by band of SOC), and the absolute mode
  reads it as one in every cell.  Relative to the pack median it cancels, and the
  capacities are learned relative to the median cell, whose own capacity stays at the
  profile's.  The pack's common level is therefore not observed: the σ published
  (:attr:`CapacityEstimator.capacity_std_ah`) adds the prior's relative σ for it to the
  learned variance, which is that of the cell against the median.  For the same reason
  ``σ²_e`` is then the innovation variance without the SOC filter's current-dependent and
  learned model-error terms (its state spread and the constant voltage noise only): the
  model error those terms stand for is the part that cancels.  A one-cell pack learns
  nothing in this mode.
- ``"absolute"``: each cell's own innovation.
- ``"off"``: frozen at the profile's capacity (the filter then runs exactly as before).

Why a dual EKF, not Plett's weighted total least squares of ``Ah`` against ``ΔSOC``: WTLS
takes ``ΔSOC`` from the SOC filter, which (above) follows the coulomb count with the
capacity it was given; measured on the 5 %-spread demo pack, two-point ``Ah / ΔSOC`` from
the frozen filter's SOC recovered almost none of the spread (errors −5.6..0 % against the
frozen −6.1..+2.8 %).  The dual EKF reads the voltage directly.

Robustness: no update from a cell whose SOC σ is above ``identify_below_soc_std`` or whose
inputs are stale; φ stays within ``1/(1 ± capacity_bounds_rel)`` of nominal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from service.cell.units import SECONDS_PER_HOUR

CapacityMode = Literal["off", "pack-relative", "absolute"]


@dataclass
class CapacityState:
    """Per-cell state of :class:`CapacityEstimator` (arrays ``[N]``)."""

    phi: np.ndarray  # Q_nominal / Q
    var: np.ndarray  # variance of phi
    sens: np.ndarray  # dSOC+/dphi of the SOC filter's posterior


class CapacityEstimator:
    """Dual EKF over ``φ = Q_nominal / Q`` for ``n_cells`` cells (see the module docstring)."""

    STATE_KEYS = ("capacity_phi", "capacity_var", "capacity_sens")

    def __init__(self, n_cells: int, nominal_ah: float, mode: CapacityMode, init_std_rel: float,
                 bounds_rel: float, inflation: float, walk_rel_per_sqrt_s: float) -> None:
        self.n = int(n_cells)
        self.nominal_ah = float(nominal_ah)
        self.mode = mode
        self.inflation = float(inflation)
        self.walk = float(walk_rel_per_sqrt_s)
        self.bounds = (1.0 / (1.0 + bounds_rel), 1.0 / (1.0 - bounds_rel))
        #: variance of the pack's common level, which the pack-relative mode never learns
        self.common_var = init_std_rel ** 2 if mode == "pack-relative" else 0.0
        self.state = CapacityState(np.ones(self.n), np.full(self.n, init_std_rel ** 2), np.zeros(self.n))

    # -- what the SOC filter uses ---------------------------------------------------------
    @property
    def capacity_ah(self) -> np.ndarray:
        return self.nominal_ah / self.state.phi

    @property
    def capacity_std_ah(self) -> np.ndarray:
        """σ of the capacity, first order: ``Q_nom / φ² · σ_φ``, with ``σ_φ²`` the learned variance
        plus, in the pack-relative mode, the unobserved common level's (the module docstring)."""
        var = np.maximum(self.state.var, 0.0) + self.common_var
        return self.nominal_ah * np.sqrt(var) / self.state.phi ** 2

    def soc_process_var(self, current_a: np.ndarray, dt_s: float) -> np.ndarray:
        """SOC variance one step adds through the capacity's uncertainty."""
        d = current_a * dt_s / (SECONDS_PER_HOUR * self.nominal_ah)
        return d * d * self.state.var

    # -- one sample --------------------------------------------------------------------------
    def update(self, current_a: np.ndarray, dt_s: float, innovation: np.ndarray, innovation_var: np.ndarray,
               ocv_slope: np.ndarray, soc_gain: np.ndarray, usable: np.ndarray,
               innovation_var_own: np.ndarray | None = None) -> np.ndarray:
        """Advance with this sample's SOC-filter outputs; returns the SOC shift ``s⁺ δφ`` to
        apply to the filter's posterior (zeros where nothing was learned).

        ``innovation_var_own``: the innovation variance without the filter's current-dependent and
        learned model-error terms (state spread and the constant voltage noise).  The pack-relative
        mode uses it, since the model error common to the pack cancels in its measurement; without
        it, ``innovation_var``."""
        st = self.state
        s_minus = st.sens - current_a * dt_s / (SECONDS_PER_HOUR * self.nominal_ah)
        h = ocv_slope * s_minus
        e = np.where(usable, innovation, 0.0)
        var_e = innovation_var
        if self.mode == "pack-relative":
            if usable.sum() >= 2:
                e = np.where(usable, e - np.median(innovation[usable]), 0.0)
            else:
                usable = np.zeros_like(usable)
            if innovation_var_own is not None:
                var_e = innovation_var_own
        p = st.var + self.walk * self.walk * max(dt_s, 0.0)
        s = h * h * p + self.inflation * var_e
        k = np.where(usable, p * h / s, 0.0)
        phi = np.clip(st.phi + k * e, *self.bounds)
        d_phi = phi - st.phi
        st.phi = phi
        st.var = p - k * h * p
        st.sens = s_minus * (1.0 - soc_gain * ocv_slope)
        return st.sens * d_phi

    def restart(self, cells: np.ndarray) -> None:
        """A SOC restart of ``cells``: the capacity is kept, the SOC sensitivity starts over."""
        self.state.sens[cells] = 0.0

    # -- persistence ---------------------------------------------------------------------
    def get_state(self) -> dict[str, np.ndarray]:
        st = self.state
        return dict(zip(self.STATE_KEYS, (st.phi, st.var, st.sens)))

    def set_state(self, arrays: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        phi, var, sens = arrays
        self.state = CapacityState(np.clip(phi, *self.bounds), np.maximum(var, 0.0), sens)
