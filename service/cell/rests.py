"""Rests on a noisy current sensor: where no current flows, read the same way by ``socd fit``
(OCV tests, HPPC rests, relaxation) and ``socd diagnose`` (the signatures read in rests).

A rest is a run of samples whose current is below a level set as a fraction of 1C. On a large
cell that level sits far above the sensor's noise and one sample says whether it rests. On a
small cell, or behind a noisy pack sensor, the noise alone can cross the level (5 mA on a
0.17 Ah cell is 3 % of 1C) and would cut every rest into pieces; there a rest is where the
current's running mean is below the level (:func:`resting`).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter1d, uniform_filter1d

#: ``socd fit``'s rest: |I| below this fraction of 1C (:func:`resting`'s default level)
REST_CURRENT_C = 0.01
#: the current sensor's noise σ is read on the samples below this fraction of 1C (rests and the
#: slowest currents; the noise of a rest is centred on zero)
NOISE_BAND_C = 0.05
#: :func:`resting` tests each sample against its level while the noise σ is at most this
#: fraction of it
REST_PER_SAMPLE_NOISE = 1.0 / 3.0
#: where the noise is larger, :func:`resting` averages the current over
#: enough samples that the mean's noise is this many times smaller than that level (a rest's mean then
#: crosses it about once in two million samples), and no single rest sample lies further than this many
#: σ from it (a load pulse does at once)
REST_NOISE_SIGMAS = 5.0
#: the longest average :func:`resting` takes (s): wider would blur a rest's edges by minutes (a
#: slowly logged test averages fewer samples, and its rests may stay cut by the noise)
REST_MAX_AVERAGE_S = 120.0


def current_noise_a(current_a: np.ndarray, capacity_ah: float) -> float:
    """The current sensor's noise σ [A]: what the current changes by from one sample to the next
    where both lie within :data:`NOISE_BAND_C` of zero (rests and the lightest loads), read robustly
    (1.4826 × the median absolute difference, over √2).  A sensor offset and a drive's light loads
    (coasting at a few % of 1C) move the current's level, not its sample-to-sample spread, so
    neither counts as noise.  0 for a logger that records rests as exact zeros."""
    quiet = np.abs(current_a) < NOISE_BAND_C * capacity_ah
    steps = np.diff(current_a)[quiet[1:] & quiet[:-1]]
    return float(1.4826 * np.median(np.abs(steps)) / np.sqrt(2.0)) if steps.size else 0.0


def _rest_level(level: float, sigma: float) -> float:
    """:func:`rest_level_a` from the level and the noise σ, both in A."""
    return level if sigma <= REST_PER_SAMPLE_NOISE * level else level + REST_NOISE_SIGMAS * sigma


def rest_level_a(current_a: np.ndarray, capacity_ah: float, level_c: float = REST_CURRENT_C) -> float:
    """The largest |I| [A] a rest sample shows: ``level_c · C``, plus :data:`REST_NOISE_SIGMAS`
    noise σ where the sensor's noise (:func:`current_noise_a`) is too large for that level alone."""
    return _rest_level(level_c * capacity_ah, current_noise_a(np.asarray(current_a, dtype=float), capacity_ah))


def load_level_a(current_a: np.ndarray, capacity_ah: float) -> float:
    """A current [A] that is load beyond doubt: five times ``REST_CURRENT_C · C``, and beyond any
    rest sample (:func:`rest_level_a`)."""
    return max(5.0 * REST_CURRENT_C * capacity_ah, rest_level_a(current_a, capacity_ah))


def resting(time_s: np.ndarray, current_a: np.ndarray, capacity_ah: float,
            level_c: float = REST_CURRENT_C) -> np.ndarray:
    """Rest samples: ``|I| < level_c · C``, where the sensor's noise (:func:`current_noise_a`)
    stays well within that.  Where it does not, a rest is where the current's running mean (over
    enough samples to bring the noise under the level, within :data:`REST_MAX_AVERAGE_S`) is below
    it: no current flows on average.  A rest then reaches back to its edges by up to half that
    window through samples within the noise of the level, so a load pulse ends it where the pulse
    begins, and a current under the noise (C/20 on a small cell) within half a window."""
    current_a = np.asarray(current_a, dtype=float)
    level = level_c * capacity_ah
    sigma = current_noise_a(current_a, capacity_ah)
    top = _rest_level(level, sigma)
    if top == level:
        return np.abs(current_a) < level
    period_s = float(np.median(np.diff(time_s))) if len(time_s) > 1 else 1.0
    longest = max(1, int(REST_MAX_AVERAGE_S / max(period_s, 1e-9)))
    width = min(longest, int(np.ceil((REST_NOISE_SIGMAS * sigma / level) ** 2))) | 1
    mean = uniform_filter1d(current_a, size=width, mode="nearest")
    quiet = np.abs(current_a) < top
    return maximum_filter1d((np.abs(mean) < level) & quiet, size=width, mode="nearest") & quiet
