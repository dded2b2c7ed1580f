"""Recursive least squares with exponential forgetting, for ``N`` independent problems at once.

For each problem ``n`` (a cell) with regressor ``φ_k`` and target ``y_k``:

    e_k = y_k - φ_kᵀ θ_{k-1}
    g_k = P_{k-1} φ_k / (λ + φ_kᵀ P_{k-1} φ_k)
    θ_k = θ_{k-1} + g_k e_k
    P_k = (P_{k-1} - g_k φ_kᵀ P_{k-1}) / λ

(the textbook form Hu & Wang cite but do not write out, their Sec. III).  Two guards
an online identifier needs and the textbook leaves out:

* ``max_trace`` — with forgetting and no excitation (a long rest) ``P`` grows as
  ``λ^-k`` ("wind-up") and the first pulse after the rest throws ``θ`` about; ``P``
  is scaled down whenever its trace exceeds the cap.
* ``P`` is re-symmetrised after every update so round-off cannot make it indefinite.

A mask skips the update for chosen problems (no new information, or a bad sample).
"""

from __future__ import annotations

import numpy as np


class Rls:
    """RLS with forgetting over ``N`` problems of ``p`` parameters: ``θ [N,p]``, ``P [N,p,p]``."""

    def __init__(
        self,
        theta0: np.ndarray,
        p0: float | np.ndarray = 1.0,
        forgetting: float = 0.999,
        max_trace: float | None = None,
        n: int | None = None,
    ) -> None:
        theta0 = np.asarray(theta0, dtype=float)
        if theta0.ndim == 1:
            theta0 = np.broadcast_to(theta0, (1 if n is None else n, theta0.size))
        self.theta = np.array(theta0, dtype=float)
        n_prob, p = self.theta.shape
        p0 = np.asarray(p0, dtype=float)
        if p0.ndim == 0:
            p0 = p0 * np.eye(p)
        elif p0.ndim == 1:
            p0 = np.diag(p0)
        self.P = np.array(np.broadcast_to(p0, (n_prob, p, p)), dtype=float)
        if not 0.0 < forgetting <= 1.0:
            raise ValueError(f"forgetting factor must be in (0, 1], got {forgetting}")
        self.forgetting = float(forgetting)
        self.max_trace = max_trace

    @property
    def n_params(self) -> int:
        return self.theta.shape[1]

    def predict(self, phi: np.ndarray) -> np.ndarray:
        """``φᵀ θ`` for every problem (the a-priori model output)."""
        return np.einsum("np,np->n", phi, self.theta)

    def update(self, phi: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """One RLS step; returns the a-priori error ``e_k`` ``[N]``."""
        phi = np.asarray(phi, dtype=float)
        y = np.asarray(y, dtype=float)
        lam = self.forgetting
        err = y - self.predict(phi)
        p_phi = np.einsum("npq,nq->np", self.P, phi)
        denom = lam + np.einsum("np,np->n", phi, p_phi)
        gain = p_phi / denom[:, None]
        theta = self.theta + gain * err[:, None]
        P = (self.P - np.einsum("np,nq->npq", gain, p_phi)) / lam
        P = 0.5 * (P + np.swapaxes(P, 1, 2))
        if self.max_trace is not None:
            tr = np.einsum("npp->n", P)
            scale = np.where(tr > self.max_trace, self.max_trace / np.maximum(tr, 1e-300), 1.0)
            P = P * scale[:, None, None]
        if mask is None:
            self.theta, self.P = theta, P
        else:
            m = np.asarray(mask, dtype=bool)
            self.theta = np.where(m[:, None], theta, self.theta)
            self.P = np.where(m[:, None, None], P, self.P)
        return err
