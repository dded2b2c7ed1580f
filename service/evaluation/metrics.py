"""Scores of an SOC estimate against truth (DESIGN §7)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CONVERGENCE_BAND_PCT = 2.0
CONVERGENCE_HOLD_S = 60.0
SETTLE_S = 600.0


@dataclass
class Scores:
    soc_rmse_pct: float
    soc_mae_pct: float
    soc_max_pct: float
    soc_rmse_after_600s_pct: float | None
    convergence_s: float | None
    v_rmse_mv: float | None
    #: share of the samples after the first 600 s whose error is within twice the estimator's own
    #: SOC σ (95 % for an honest Gaussian σ); None for an estimator that reports no σ
    soc_within_2sigma_pct: float | None


def convergence_time(time_s: np.ndarray, err_pct: np.ndarray, band: float = CONVERGENCE_BAND_PCT,
                     hold_s: float = CONVERGENCE_HOLD_S) -> float | None:
    """First time (from the start) at which |error| < ``band`` and stays so for ``hold_s``.

    The hold must be inside the recording; ``None`` if that never happens.
    """
    t = time_s - time_s[0]
    inside = np.abs(err_pct) < band
    # index of the next sample outside the band, for every sample
    n = t.size
    next_out = np.full(n, n)
    out_idx = np.flatnonzero(~inside)
    if out_idx.size:
        pos = np.searchsorted(out_idx, np.arange(n))
        valid = pos < out_idx.size
        next_out[valid] = out_idx[pos[valid]]
    end_time = np.where(next_out < n, t[np.minimum(next_out, n - 1)], np.inf)
    ok = inside & (end_time - t >= hold_s) & (t + hold_s <= t[-1])
    if not ok.any():
        return None
    return float(t[np.argmax(ok)])


def within_2sigma_pct(err_pct: np.ndarray, soc_std: np.ndarray) -> float:
    """Share (%) of the samples whose SOC error (in %) lies within twice the σ published with them
    (a fraction): 95 % for an honest Gaussian σ."""
    return float(100.0 * np.mean(np.abs(err_pct) <= 200.0 * soc_std))


def score(time_s: np.ndarray, soc_est: np.ndarray, soc_true: np.ndarray,
          v_pred: np.ndarray | None = None, v_meas: np.ndarray | None = None,
          soc_std: np.ndarray | None = None) -> Scores:
    err = 100.0 * (soc_est - soc_true)
    after = (time_s - time_s[0]) >= SETTLE_S
    v_rmse = None
    if v_pred is not None and v_meas is not None:
        v_rmse = float(1000.0 * np.sqrt(np.mean((v_pred - v_meas) ** 2)))
    within = None
    if soc_std is not None and after.any():
        within = within_2sigma_pct(err[after], soc_std[after])
    return Scores(
        soc_rmse_pct=float(np.sqrt(np.mean(err**2))),
        soc_mae_pct=float(np.mean(np.abs(err))),
        soc_max_pct=float(np.max(np.abs(err))),
        soc_rmse_after_600s_pct=float(np.sqrt(np.mean(err[after] ** 2))) if after.any() else None,
        convergence_s=convergence_time(time_s, err),
        v_rmse_mv=v_rmse,
        soc_within_2sigma_pct=within,
    )
