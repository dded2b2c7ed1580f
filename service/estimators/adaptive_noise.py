"""Adaptive measurement noise by covariance matching, shared by every SOC filter and the fast
identifier (:class:`service.estimators.parameter_ekf.ParameterEkf`).

Mehra (1972), the Sage-Husa family of adaptive Kalman filters: the innovation ``e``
has variance ``S + R_extra``, so the excess of ``e²`` over the predicted spread ``S``,
averaged over about ``samples`` steps, estimates the model error's variance
``R_extra``.  An outlier (a wild voltage, a divergence) must not buy itself a larger
noise: each sample's ``e²`` counts at most :data:`ADAPT_CLIP`² times the current
spread (Huber-style), so divergence detection still sees it.

Two shapes of ``R_extra`` (:class:`AdaptiveNoise`):

* ``uniform``: one variance for every sample, ``R ← (1-β)·R + β·excess``.
* ``load``: ``R_extra = a + c·φ`` with ``φ = (|I|·R_total)²``, the squared modelled
  overpotential.  An equivalent-circuit model's error is mostly under load (the
  overpotential's shape, not the OCV), so a single variance learned from loaded samples
  would also drown the rests, where the voltage is close to the OCV and says most about
  SOC.  ``a`` and ``c`` are the weighted least-squares fit of the clipped excess on
  ``[1, φ]`` from exponentially weighted moments; where ``φ`` barely varies (no rests,
  a constant current) the fit is not determined and the uniform estimate is used.

Correlated model error (``correlation_cap`` > 1).  The filter takes each sample's error as
independent of the last.  A model error that persists for minutes (a cold cell's wrong
diffusion, an OCV offset) is not: with lag-1 autocorrelation ``ρ`` of the innovation, ``N``
samples carry the information of about ``N·(1-ρ)/(1+ρ)`` independent ones (the variance
inflation factor of an AR(1) sequence's mean, e.g. Bayley & Hammersley 1946), so the learned
``R_extra`` is multiplied by ``(1+ρ)/(1-ρ)``, at most ``correlation_cap``.  ``ρ`` is
estimated from exponentially weighted moments ``E[e·e₋₁]`` and ``E[e²]`` over the same
window.  The factor scales only the learned extra, so a model that fits well (``R_extra ≈ 0``)
is not slowed, however correlated its small residual.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

#: one sample's squared innovation counts at most this many σ² of the spread
ADAPT_CLIP = 3.0
#: moments kept per cell: E[1], E[φ], E[φ²], E[excess], E[excess·φ] (the noise's shape),
#: then E[e·e₋₁] and E[e²] (the innovation's lag-1 autocorrelation)
N_MOMENTS = 7
#: the shape moments alone: states written before the autocorrelation was kept
N_SHAPE_MOMENTS = 5
#: ρ is clipped below this, so the inflation factor stays finite before the cap
MAX_CORRELATION = 0.999


class AdaptiveNoise:
    """Covariance-matched extra measurement variance for ``n_cells`` cells (module docstring)."""

    def __init__(self, n_cells: int, samples: int, shape: Literal["uniform", "load"] = "uniform",
                 correlation_cap: float = 1.0) -> None:
        self.samples = samples
        self.shape = shape
        self.correlation_cap = correlation_cap
        #: exponentially weighted moments, see :data:`N_MOMENTS`
        self.moments = np.zeros((n_cells, N_MOMENTS))
        #: each cell's last innovation where it was matched (V), for E[e·e₋₁]
        self.previous = np.zeros(n_cells)

    def reset(self, cells: np.ndarray) -> None:
        self.moments[cells] = 0.0
        self.previous[cells] = 0.0

    def inflation(self) -> np.ndarray | float:
        """``(1+ρ)/(1-ρ)`` per cell, at most ``correlation_cap`` (module docstring); 1 when off."""
        if self.correlation_cap <= 1.0:
            return 1.0
        lagged, square = self.moments[:, 5], self.moments[:, 6]
        rho = np.clip(lagged / np.maximum(square, 1e-30), 0.0, MAX_CORRELATION)
        return np.minimum((1.0 + rho) / (1.0 - rho), self.correlation_cap)

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """``(a, c)`` of ``R_extra = a + c·φ`` per cell."""
        m0, m1, m2, y0, y1 = self.moments[:, :N_SHAPE_MOMENTS].T
        if self.shape == "uniform":
            return y0, np.zeros_like(y0)
        det = m0 * m2 - m1 * m1
        # enough weight and spread in φ for two coefficients; else the uniform estimate
        ok = (m0 > 0.05) & (det > 1e-3 * m0 * m2) & (m2 > 0)
        safe = np.where(ok, det, 1.0)
        a = np.where(ok, (y0 * m2 - m1 * y1) / safe, y0)
        c = np.where(ok, (m0 * y1 - m1 * y0) / safe, 0.0)
        # non-negative variances: a constrained fit on the boundary
        neg_c = c < 0
        a = np.where(neg_c, y0, a)
        c = np.where(neg_c, 0.0, c)
        neg_a = a < 0
        c = np.where(neg_a, np.where(m2 > 0, y1 / np.where(m2 > 0, m2, 1.0), 0.0), c)
        a = np.where(neg_a, 0.0, a)
        return a, c

    def extra(self, phi: np.ndarray) -> np.ndarray:
        """``R_extra`` (V²) at squared overpotential ``phi``."""
        a, c = self.coefficients()
        return a + c * phi

    def match(self, innovation: np.ndarray, s: np.ndarray, phi: np.ndarray,
              update: np.ndarray | bool = True) -> np.ndarray:
        """``S + f·R_extra`` for predicted innovation variance ``s`` and inflation factor ``f``
        (:meth:`inflation`); updates the moments where ``update``."""
        extra = self.extra(phi)
        # the excess is clipped against the uninflated spread, so the factor does not feed itself
        excess = np.maximum(np.minimum(innovation * innovation, ADAPT_CLIP**2 * (s + extra)) - s, 0.0)
        s_tot = s + self.inflation() * extra
        beta = 1.0 / self.samples
        sample = np.stack([np.ones_like(phi), phi, phi * phi, excess, excess * phi,
                           innovation * self.previous, innovation * innovation], axis=1)
        new = (1.0 - beta) * self.moments + beta * sample
        updated = np.broadcast_to(update, self.previous.shape)
        self.moments = np.where(updated[:, None], new, self.moments)
        self.previous = np.where(updated, innovation, self.previous)
        return s_tot

    def set_moments(self, moments: np.ndarray, previous: np.ndarray | None = None) -> None:
        """Restore the moments (and last innovations); states with only the shape moments
        (:data:`N_SHAPE_MOMENTS` columns) start the autocorrelation from zero."""
        moments = np.asarray(moments, dtype=float)
        self.moments = np.zeros((moments.shape[0], N_MOMENTS))
        self.moments[:, :moments.shape[1]] = moments
        self.previous = (np.zeros(moments.shape[0]) if previous is None
                         else np.array(previous, dtype=float, copy=True))
