"""Clean current steps in a recording: where the Butler-Volmer curvature can be read.

A clean step moves the current by at least :data:`STEP_MIN_C` × 1C between two samples with the
current steady in the sample before and the one after. The diagnosis's kinetics signature
(:func:`service.diagnosis.signatures.step_kinetics`) reads the apparent exchange current across
them, and ``socd fit`` fits the exchange current only at temperatures whose recordings have enough
of them (:func:`steps_resolve_kinetics`): one rule for both.
"""

from __future__ import annotations

import numpy as np

#: current steps between two samples of at least this C-rate ...
STEP_MIN_C = 0.2
#: ... with the current steady (within this share of 1C, plus 1 % of |I|) in the samples either side
STEP_STEADY_C = 0.02
#: at least this many such steps ...
STEP_MIN_STEPS = 20
#: ... reaching at least this C-rate (the curvature of asinh needs a current well above i0)
STEP_MIN_PEAK_C = 0.5


def current_steps(time_s: np.ndarray, current_a: np.ndarray, capacity_ah: float,
                  usable: np.ndarray | None = None) -> np.ndarray:
    """Indices ``j`` of clean current steps (module docstring): the current moves by at
    least :data:`STEP_MIN_C` × 1C from sample ``j`` to ``j + 1`` and is steady in the sample before
    and the one after. ``usable`` (optional mask): only steps whose four samples lie inside it."""
    n = current_a.size
    if n < 4:
        return np.zeros(0, dtype=int)
    dt = np.diff(time_s)
    di = np.diff(current_a)
    j = np.arange(1, n - 2)
    steady = STEP_STEADY_C * capacity_ah
    ok = ((np.abs(di[j]) >= STEP_MIN_C * capacity_ah)
          & (np.abs(di[j - 1]) <= steady + 0.01 * np.abs(current_a[j]))
          & (np.abs(di[j + 1]) <= steady + 0.01 * np.abs(current_a[j + 1]))
          & (dt[j] <= 2.0 * float(np.median(dt))))
    if usable is not None:
        ok &= usable[j - 1] & usable[j] & usable[j + 1] & usable[j + 2]
    return j[ok]


def steps_peak_c(current_a: np.ndarray, steps: np.ndarray, capacity_ah: float) -> float:
    """The largest |current| [C-rate] on either side of the ``steps``."""
    if not steps.size:
        return 0.0
    return float(np.max(np.abs(np.concatenate([current_a[steps], current_a[steps + 1]])))) / capacity_ah


def steps_resolve_kinetics(n_steps: int, peak_c: float) -> bool:
    """Enough current steps, reaching high enough, for the Butler-Volmer curvature to be measured:
    :data:`STEP_MIN_STEPS` steps reaching :data:`STEP_MIN_PEAK_C`. The kinetics signature reads
    nothing below this, and ``socd fit`` does not fit the exchange current from data below it."""
    return n_steps >= STEP_MIN_STEPS and peak_c >= STEP_MIN_PEAK_C
