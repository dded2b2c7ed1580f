"""Refit the base model jointly with one extension, on the fit part of a recording.

The base coordinates (:mod:`service.cell.fitting`) and the extension's coordinates are
fitted together with :func:`scipy.optimize.least_squares` (``trf``, bounds), because a
base model fitted without the missing physics has bent its parameters to hide it
(e.g. ``R_ct`` averages over a current-dependent resistance).  The extension's
nonlinear coordinates get a few starting points, tried in one vectorised pass.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from service.cell.fitting import FitSegment, search_bounds
from service.cell.profile import CellProfile
from service.diagnosis.effects import Context, Effect
from service.diagnosis.simulation import base_mods, simulate_candidates


@dataclass
class Problem:
    """The fit grid, the fit mask and what is fixed about the cell."""

    profile: CellProfile
    grid: FitSegment  # whole recording, block-averaged
    fit_mask: np.ndarray  # samples of ``grid`` in the fit part
    v_rest0: float
    temp_c: float  # temperature of the base parameter point (Arrhenius reference)
    memory_length: int
    ctx: Context | None = None

    def residuals(self, x: np.ndarray, effect: Effect | None) -> np.ndarray:
        """``[N, n_fit]`` simulated minus measured on the fit part."""
        x = np.atleast_2d(x)
        mods = base_mods(x[:, :7], self.profile, self.temp_c)
        if effect is not None:
            effect.apply(x[:, 7:], mods, self.ctx)
        v, _ = simulate_candidates(self.profile, self.grid, mods, self.v_rest0, self.memory_length)
        r = (v.T - self.grid.voltage_v[None, :])[:, self.fit_mask]
        return np.where(np.isfinite(r), np.clip(r, -5.0, 5.0), 5.0)


@dataclass
class RefitResult:
    x: np.ndarray
    rss: float
    n: int
    jac: np.ndarray | None
    seconds: float


def refit(problem: Problem, x_base: np.ndarray, effect: Effect | None, max_seconds: float = 20.0,
          max_nfev: int = 40) -> RefitResult:
    t0 = time.perf_counter()
    base = search_bounds(problem.profile.effective_capacity_ah)
    bounds = list(base.values()) + (list(effect.bounds) if effect else [])
    lo, hi = np.array(bounds, dtype=float).T
    # starting points: the base fit plus each of the extension's starts, one vectorised pass
    if effect is None:
        starts = np.atleast_2d(x_base)
    else:
        bases = [x_base] + (list(effect.base_variants(x_base, problem.ctx)) if effect.base_variants else [])
        starts = np.array([np.concatenate([b, s]) for b in bases for s in effect.starts(problem.ctx)])
    starts = np.clip(starts, lo + 1e-9, hi - 1e-9)
    r0 = problem.residuals(starts, effect)
    x_start = starts[int(np.argmin(np.sum(r0**2, axis=1)))]
    deadline = t0 + max_seconds
    steps = np.full(lo.size, 1e-4)
    best = {"x": x_start, "cost": float(np.min(np.sum(r0**2, axis=1))), "jac": None}
    cache: dict[bytes, np.ndarray] = {}

    class _Stop(Exception):
        pass

    def fun(x):
        key = x.tobytes()
        r = cache.get(key)
        if r is None:
            if time.perf_counter() > deadline:
                raise _Stop
            r = problem.residuals(x, effect)[0]
        c = float(r @ r)
        if c < best["cost"]:
            best.update(x=x.copy(), cost=c)
        return r

    def jac(x):
        if time.perf_counter() > deadline:
            raise _Stop
        h = steps * np.where(x + steps > hi, -1.0, 1.0)
        r = problem.residuals(np.vstack([x, x + np.diag(h)]), effect)
        cache.clear()
        cache[x.tobytes()] = r[0]
        j = ((r[1:] - r[0]) / h[:, None]).T
        if np.allclose(x, best["x"]):
            best["jac"] = j
        return j

    try:
        sol = least_squares(fun, x_start, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                            max_nfev=max_nfev, xtol=1e-6, ftol=1e-5)
        if sol.cost * 2 <= best["cost"] + 1e-15:
            best.update(x=sol.x, cost=float(2 * sol.cost), jac=sol.jac)
    except _Stop:
        pass
    return RefitResult(x=best["x"], rss=best["cost"], n=int(problem.fit_mask.sum()), jac=best["jac"],
                       seconds=time.perf_counter() - t0)


def parameter_std(result: RefitResult, n_eff: float) -> np.ndarray | None:
    """Standard errors of the coordinates from ``(JᵀJ)⁻¹ σ²``, inflated for correlated residuals.

    ``σ²`` is the residual variance; the inflation ``n / n_eff`` accounts for residual
    autocorrelation (each sample is not an independent observation).
    """
    if result.jac is None:
        return None
    j = result.jac
    sigma2 = result.rss / max(result.n - j.shape[1], 1)
    try:
        cov = np.linalg.pinv(j.T @ j) * sigma2 * (result.n / max(n_eff, 1.0))
    except np.linalg.LinAlgError:
        return None
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))
