"""The G-L short memory as a span of time, whatever the sample period.

Zeng Eq. 2 truncates the Grünwald-Letnikov sum after ``L`` samples, so the memory spans
``L · h`` seconds.  What the truncation does to a CPE branch depends on that span: under a
steady current the truncated derivative acts as an extra leak of about
``(L h)^-α / Γ(1 - α)``, so a point fitted at one sample period, run with the same ``L`` at
another, is a different branch (a profile fitted on 1 s samples run at 10 Hz keeps a tenth of
its memory).  ``socd fit`` therefore stores the span it fitted with
(:attr:`service.cell.profile.CellProfile.memory_span_s`), and the estimators run the model with
``L = span / h`` at their own sample period (Podlubny's short-memory principle states the memory
as a time, not a count).
"""

from __future__ import annotations

import numpy as np

#: the longest G-L memory a model is run with, in samples (the estimator settings' bound)
MAX_MEMORY_LENGTH = 512


def median_interval_s(dt_s: np.ndarray) -> float | None:
    """The median of the positive intervals ``dt_s`` (rests logged more sparsely are few
    samples); None without one."""
    dt = np.asarray(dt_s, dtype=float)
    dt = dt[dt > 0]
    return float(np.median(dt)) if dt.size else None


def sample_period_s(time_s: np.ndarray) -> float | None:
    """A recording's sample period: :func:`median_interval_s` of its time stamps."""
    return median_interval_s(np.diff(np.asarray(time_s, dtype=float)))


def memory_length_at(span_s: float | None, period_s: float | None, default: int) -> int:
    """The G-L memory length in samples that spans ``span_s`` at ``period_s`` (1 to
    :data:`MAX_MEMORY_LENGTH`); ``default`` when either is unknown."""
    if span_s is None or period_s is None or not np.isfinite(period_s) or period_s <= 0:
        return int(default)
    return int(np.clip(round(span_s / period_s), 1, MAX_MEMORY_LENGTH))
