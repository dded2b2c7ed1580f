"""Adaptive measurement noise by covariance matching, shared by every SOC filter.

Mehra (1972), the Sage-Husa family of adaptive Kalman filters: the innovation ``e``
has variance ``S + R_extra``, so the excess of ``e²`` over the predicted spread ``S``,
averaged over about ``samples`` steps, estimates the model error's variance
``R_extra``.  An outlier (a wild voltage, a divergence) must not buy itself a larger
noise: each sample's ``e²`` counts at most :data:`ADAPT_CLIP`² times the current
spread (Huber-style), so divergence detection still sees it.
"""

from __future__ import annotations

import numpy as np

#: one sample's squared innovation counts at most this many σ² of the spread
ADAPT_CLIP = 3.0


def matched_noise(r_adapt: np.ndarray, innovation: np.ndarray, s: np.ndarray, samples: int,
                  update: np.ndarray | bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(S + R_extra, new R_extra)`` for predicted innovation variance ``s`` (without the
    adaptive part); ``R_extra`` moves only where ``update`` (e.g. cells with a measurement)."""
    s_tot = s + r_adapt
    excess = np.maximum(np.minimum(innovation * innovation, ADAPT_CLIP**2 * s_tot) - s, 0.0)
    beta = 1.0 / samples
    return s_tot, np.where(update, (1.0 - beta) * r_adapt + beta * excess, r_adapt)
