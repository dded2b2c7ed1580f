"""The SOC error the filter does not model, for the σ it publishes (a Schmidt consider analysis).

The SOC filter (Zeng Table 3) reads every voltage sample as new evidence with white noise.
Two errors break that and are not filter states by default:

- the OCV table's error at the present SOC, ``o``: the same for every sample while the SOC
  stays put, so a few hundred samples of it shrink the filter's σ as if they were independent;
- a current-sensor offset, ``b`` (fraction of 1C): the coulomb count drifts with it.

The filter's own σ then settles far below its error (docs/results/tuning.md measures how far).
This module carries the covariance of the SOC error those two cause, ``c``, beside the filter,
with the gains the filter actually used: Schmidt's "consider" analysis, the true covariance of a
filter that leaves some parameters out of its state:

    predict:  c ← c + (Δt / 3600) · b                      (Zeng Eq. 4 with the offset)
              o ← φ o + √(1 - φ²) σ_o w,  φ = exp(-|ΔSOC| / L)
    update:   c ← (1 - K s) · c + K · o                      (s = dOCV/dSOC, K the SOC gain)

``o`` is a Gauss-Markov process in SOC, as the filter's optional OCV-error state is
(``ocv_error_soc_length``), and ``b`` is constant. The SOC published is unchanged; its σ²
is the filter's own variance plus ``Var(c)`` (:attr:`ConsiderCovariance.soc_var`).
Nothing here feeds back into the estimate, the gains or any gate on the filter's σ.

A filter that estimates one of the two itself (``ocv_error_std_v > 0`` or
``current_bias_state``) has it in its own covariance; :func:`considered_priors` leaves it
out here. With a multi-innovation window (Zeng Eq. 20) the gain used is this sample's; the
window spreads the same correction over its samples, so the recursion is approximate there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.cell.units import SECONDS_PER_HOUR
from service.estimators.settings import EstimatorSettings

#: the covariance's distinct entries, in the order :attr:`ConsiderCovariance.entries` holds them
ENTRIES = ("cc", "co", "cb", "oo", "ob", "bb")
_OO, _BB = ENTRIES.index("oo"), ENTRIES.index("bb")
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: the rows of :attr:`ConsiderCovariance.entries` that are variances (never negative)
VARIANCE_ENTRIES = tuple(ENTRIES.index(e) for e in ("cc", "oo", "bb"))
#: the largest SOC σ published: wider says nothing more about a quantity bounded to [0, 1]
MAX_REPORTED_SOC_STD = 0.5


@dataclass(frozen=True)
class ConsideredPriors:
    """σ of the errors the filter does not estimate (0: not considered)."""

    ocv_error_v: float
    current_offset_c: float
    ocv_error_soc_length: float


def considered_priors(settings: EstimatorSettings) -> ConsideredPriors:
    """The settings' considered errors, without those the filter estimates as states."""
    ocv = 0.0 if settings.ocv_error_std_v > 0 else settings.reported_ocv_error_v
    offset = 0.0 if settings.current_bias_state else settings.reported_current_offset_c
    return ConsideredPriors(ocv, offset, settings.ocv_error_soc_length)


def _finite(x: np.ndarray) -> np.ndarray:
    """``x`` as floats with NaN read as 0 and ±inf as the largest float (:func:`numpy.nan_to_num`),
    checked first, since it runs three times per filter step and the values are almost always finite."""
    x = np.asarray(x, float)
    return x if np.isfinite(x).all() else np.nan_to_num(x)


class ConsiderCovariance:
    """Covariance of ``[c, o, b]`` per cell, vectorised like the pack's filter: its six distinct
    entries (:data:`ENTRIES`) as ``[6, N]``, so a step is a few vector operations.

    ``ocv_error_v`` and ``current_offset_c`` may be per cell (``[N]``): the research sweep
    (``research.sigma_calibration``) runs one grid value per "cell" on one filter's gains."""

    def __init__(self, n_cells: int, ocv_error_v: float | np.ndarray, current_offset_c: float | np.ndarray,
                 ocv_error_soc_length: float) -> None:
        self.n = int(n_cells)
        self.ocv_var = np.broadcast_to(np.asarray(ocv_error_v, float) ** 2, (self.n,)).copy()
        self.soc_length = float(ocv_error_soc_length)
        self.entries = np.zeros((len(ENTRIES), self.n))
        self.entries[_OO] = self.ocv_var
        self.entries[_BB] = np.asarray(current_offset_c, float) ** 2  # constant: no walk to keep it for
        #: the SOC at the previous step (−1: none yet)
        self.last_soc = np.full(self.n, -1.0)

    @classmethod
    def from_settings(cls, n_cells: int, settings: EstimatorSettings) -> ConsiderCovariance:
        p = considered_priors(settings)
        return cls(n_cells, p.ocv_error_v, p.current_offset_c, p.ocv_error_soc_length)

    @property
    def soc_var(self) -> np.ndarray:
        """``Var(c) [N]``: the SOC variance the considered errors add to the filter's."""
        return self.entries[0]

    def restart(self, cells: np.ndarray) -> None:
        """A filter (re)started at a given SOC and σ: its error so far is in that σ, so ``c`` is
        zero and uncorrelated; the table error and the offset keep what is known of them."""
        self.entries[:3, cells] = 0.0
        self.last_soc[cells] = -1.0

    def step(self, dt_s: float, soc: np.ndarray, soc_gain: np.ndarray, ocv_slope: np.ndarray) -> None:
        """One sample: the offset's drift over ``dt_s``, the table error's decorrelation as the
        SOC moves, then the filter's update with SOC gain ``soc_gain [N]`` (0 where a cell took
        no voltage) at OCV slope ``ocv_slope [N]`` (V per unit SOC).  Written out entry by entry
        (the covariance is symmetric), which is cheaper than a 3×3 matrix product per cell."""
        cc, co, cb, oo, ob, bb = self.entries
        g = max(float(dt_s), 0.0) / SECONDS_PER_HOUR  # c += g·b
        cc, co, cb = cc + 2.0 * g * cb + g * g * bb, co + g * ob, cb + g * bb
        soc = _finite(soc)
        moved = np.where(self.last_soc >= 0.0, np.abs(soc - self.last_soc), 0.0)
        phi = np.exp(-moved / self.soc_length)  # o = φ·o + √(1 - φ²)·σ_o·w
        co, ob, oo = phi * co, phi * ob, phi * phi * oo + (1.0 - phi * phi) * self.ocv_var
        k = _finite(soc_gain)
        a = np.clip(1.0 - k * _finite(ocv_slope), 0.0, 1.0)  # c = a·c + K·o
        cc, co, cb = a * a * cc + 2.0 * a * k * co + k * k * oo, a * co + k * oo, a * cb + k * ob
        self.entries = np.stack((cc, co, cb, oo, ob, bb))
        self.last_soc = soc.copy()

    @property
    def cov(self) -> np.ndarray:
        """The full covariance, ``[N, 3, 3]`` (``c``, ``o``, ``b``)."""
        full = np.empty((self.n, 3, 3))
        for (r, c), val in zip(_UPPER, self.entries):
            full[:, r, c] = full[:, c, r] = val
        return full

    def get_state(self) -> dict[str, np.ndarray]:
        return {"consider_entries": self.entries, "consider_last_soc": self.last_soc}

    def set_state(self, entries: np.ndarray, last_soc: np.ndarray) -> None:
        """Restore :meth:`get_state` output (shapes and signs checked by the caller)."""
        self.entries, self.last_soc = entries.copy(), last_soc.copy()
