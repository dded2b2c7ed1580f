"""Scaled symmetric sigma points (Zeng Table 3, steps 1 and 3), batched over cells."""

from __future__ import annotations

import numpy as np


def merwe_weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Mean and covariance weights for ``2n+1`` points (Zeng Table 3 step 1).

    Returns ``(wm, wc, gamma)`` where sigma points are ``x ± gamma * sqrt(P)``.
    """
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 1.0 / (2.0 * (n + lam)))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + (1.0 - alpha**2 + beta)
    return wm, wc, float(np.sqrt(n + lam))


def robust_cholesky(p: np.ndarray, floor: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Batched lower Cholesky factor of symmetric ``p[N, n, n]``.

    Where a cell's matrix is not positive definite, it is repaired by clipping its
    eigenvalues at ``floor`` (the repaired matrix is written back).  Returns the
    factor and a boolean mask of repaired cells, so callers can count repairs.
    """
    caller = p
    p = 0.5 * (p + np.swapaxes(p, -1, -2))
    try:
        return np.linalg.cholesky(p), np.zeros(p.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    w, v = np.linalg.eigh(p)
    bad = (w.min(axis=-1) <= floor) | ~np.isfinite(w).all(axis=-1)
    w = np.where(np.isfinite(w), np.maximum(w, floor), 1.0)
    fixed = np.einsum("...ij,...j,...kj->...ik", v, w, v)
    p[bad] = fixed[bad]
    caller[bad] = p[bad]
    return np.linalg.cholesky(0.5 * (p + np.swapaxes(p, -1, -2))), bad


def sigma_points(x: np.ndarray, sqrt_p: np.ndarray, gamma: float) -> np.ndarray:
    """``[N, 2n+1, n]`` points: ``x``, ``x + γ S_i``, ``x - γ S_i`` (Zeng Table 3 step 3)."""
    cols = gamma * np.swapaxes(sqrt_p, -1, -2)  # row i = column i of S
    return np.concatenate([x[:, None, :], x[:, None, :] + cols, x[:, None, :] - cols], axis=1)
