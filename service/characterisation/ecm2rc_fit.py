"""Textbook 2-RC characterisation: the bar every fractional-order profile is held to.

The model is the one the 2-RC EKF runs (:mod:`service.estimators.ecm2rc_ekf`, Plett 2004;
Hu & Wang Eq. 2 for the branches)::

    SOC_k = SOC_{k-1} - I_k dt_k / (3600 Q)
    x_b,k = a_b x_b,k-1 + (1 - a_b) I_k,      a_b = exp(-dt_k / τ_b)     (b = 1, 2)
    V_k   = OCV(SOC_k) - R0 I_k - R1 x_1,k - R2 x_2,k

with every branch relaxed at the start of a segment.  For fixed ``τ1, τ2`` the voltage is
linear in ``R0, R1, R2`` and in the OCV, so the fit is a bounded linear least-squares
problem (:func:`scipy.optimize.lsq_linear`) solved for every candidate pair of time
constants: the OCV as knot values on a SOC grid, monotone by construction (a free level
plus non-negative increments), with a second-difference penalty that carries it across
SOC the data does not visit, Huber weights (iteratively re-weighted) so a few bad samples
cannot pull it, and ``τ1 ∈ [1, 100] s``, ``τ2 ∈ [10, 1000] s`` so neither branch can
become an integrator that soaks up OCV or capacity error.  The pair is chosen on a
log grid and polished with a bounded Nelder-Mead in ``ln τ``.

When an OCV is already known (a table or an OCV test), it is held fixed and only the
resistances and time constants are fitted.  Where the OCV is fitted, it can be pulled
gently towards a ``prior`` row (another temperature's fit) where the data is thin.
The result is stored in the profile (:class:`service.cell.profile.Ecm2RcSpec`) and is
what ``ecm2rc-ekf`` runs on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal, sparse
from scipy.interpolate import PchipInterpolator
from scipy.optimize import lsq_linear, minimize, nnls

from service.cell.coulomb import coulomb_soc
from service.cell.fitting import FitSegment, small_cell_ratio
from service.cell.ocv import EXTRAPOLATION_SPAN, OcvTable
from service.characterisation.ocv_choices import OCV_SMOOTH_WEIGHT
from service.characterisation.segment_selection import select_segments

#: time-constant bounds of the two RC branches [s]
TAU1_BOUNDS_S = (1.0, 100.0)
TAU2_BOUNDS_S = (10.0, 1000.0)
#: the slow branch is at least this many times slower than the fast one (no label switching)
MIN_TAU_RATIO = 2.0
#: resistance bound [ohm] of a cell of BOUNDS_MIN_CAPACITY_AH or more (higher for a smaller cell: r_max_ohm)
R_MAX_OHM = 2.0
#: OCV knots on [0, 1] when the OCV is fitted
OCV_KNOTS = 81
#: Huber threshold in robust standard deviations (the usual 95 %-efficiency constant)
HUBER_K = 1.345
#: re-weighting passes of the Huber fit
HUBER_PASSES = 3
#: candidate time constants of the grid search, per branch
TAU_GRID_POINTS = 9
#: runs of equal sample interval shorter than this on average: the branch inputs are stepped sample by sample
MIN_RUN_SAMPLES = 8
#: samples at most in one fit (whole segments are thinned evenly beyond it)
MAX_FIT_SAMPLES = 40000


@dataclass(frozen=True)
class Ecm2RcFit:
    """One temperature's textbook fit: OCV knot values (``ocv_soc``, ``ocv_v``), the
    resistances [ohm] and time constants [s], and the fit RMSE [mV] on the segments."""

    ocv_soc: np.ndarray
    ocv_v: np.ndarray
    r0: float
    r1: float
    tau1_s: float
    r2: float
    tau2_s: float
    rmse_mv: float
    n_samples: int
    r_max_ohm: float = R_MAX_OHM  # the resistances' search bound (r_max_ohm)

    def ocv_on(self, grid: np.ndarray) -> np.ndarray:
        """The OCV on ``grid`` (monotone cubic through the knots; linear beyond them)."""
        inside = PchipInterpolator(self.ocv_soc, self.ocv_v, extrapolate=False)(np.clip(grid, self.ocv_soc[0], self.ocv_soc[-1]))
        return np.asarray(inside, dtype=float)

    def at_bounds(self) -> list[str]:
        """Names of the parameters that ended on a bound of the search."""
        out = []
        for name, val, (lo, hi) in (("tau1", self.tau1_s, TAU1_BOUNDS_S), ("tau2", self.tau2_s, TAU2_BOUNDS_S)):
            if val <= lo * 1.001 or val >= hi * 0.999:
                out.append(f"{name} = {val:.3g} s")
        for name, val in (("R0", self.r0), ("R1", self.r1), ("R2", self.r2)):
            if val <= 1e-6 or val >= self.r_max_ohm * 0.999:
                out.append(f"{name} = {val * 1e3:.3g} mΩ")
        return out


@dataclass(frozen=True)
class _Prepared:
    """The segments as one stacked problem: currents, voltages, interval per sample,
    SOC by coulomb counting, and where each segment starts."""

    current_a: np.ndarray
    voltage_v: np.ndarray
    dt_s: np.ndarray
    soc: np.ndarray
    starts: np.ndarray


def r_max_ohm(capacity_ah: float) -> float:
    """The resistances' upper bound for a cell of ``capacity_ah``: :data:`R_MAX_OHM`, raised below
    :data:`service.cell.fitting.BOUNDS_MIN_CAPACITY_AH` by the cell's ``small_cell_ratio``, as the
    fractional fit's resistance bounds are (a small cell's resistances are proportionally larger)."""
    return R_MAX_OHM * small_cell_ratio(capacity_ah)


def _prepare(segments: list[FitSegment], capacity_ah: float) -> _Prepared:
    cur, volt, dt, soc, starts = [], [], [], [], []
    n = 0
    for s in segments:
        starts.append(n)
        n += len(s)
        cur.append(s.current_a)
        volt.append(s.voltage_v)
        d = np.diff(s.time_s, prepend=s.time_s[0])
        dt.append(d)
        soc.append(coulomb_soc(s.time_s, s.current_a, capacity_ah, s.soc0))
    return _Prepared(np.concatenate(cur), np.concatenate(volt), np.concatenate(dt), np.concatenate(soc),
                     np.asarray(starts))


def branch_inputs(prep: _Prepared, taus_s: np.ndarray) -> np.ndarray:
    """``x[k, j]``: the current through a unit resistance's RC branch of time constant
    ``taus_s[j]`` (exact discretisation, relaxed at each segment's start).

    Within a run of equal sample intervals the recursion is a fixed first-order filter
    (:func:`scipy.signal.lfilter`, its state carried from run to run); a recording whose
    interval changes at most samples is stepped sample by sample instead."""
    taus = np.asarray(taus_s, dtype=float)
    n = prep.current_a.size
    run_start = np.ones(n, dtype=bool)
    run_start[1:] = ~np.isclose(prep.dt_s[1:], prep.dt_s[:-1], rtol=1e-9, atol=0.0)
    run_start[prep.starts] = True
    firsts = np.flatnonzero(run_start)
    if firsts.size > max(n // MIN_RUN_SAMPLES, 1):
        return _branch_inputs_stepwise(prep, taus)
    seg_start = np.zeros(n, dtype=bool)
    seg_start[prep.starts] = True
    out = np.empty((n, taus.size))
    x = np.zeros(taus.size)
    for lo, hi in zip(firsts, np.append(firsts[1:], n)):
        if seg_start[lo]:
            x[:] = 0.0
        a = np.exp(-prep.dt_s[hi - 1] / taus)
        for j, aj in enumerate(a):
            out[lo:hi, j], _ = signal.lfilter([1.0 - aj], [1.0, -aj], prep.current_a[lo:hi], zi=[aj * x[j]])
        x = out[hi - 1].copy()
    return out


def _branch_inputs_stepwise(prep: _Prepared, taus: np.ndarray) -> np.ndarray:
    """:func:`branch_inputs` one sample at a time (any sample intervals)."""
    out = np.empty((prep.current_a.size, taus.size))
    x = np.zeros(taus.size)
    is_start = np.zeros(prep.current_a.size, dtype=bool)
    is_start[prep.starts] = True
    a_all = np.exp(-prep.dt_s[:, None] / taus[None, :])
    for k in range(prep.current_a.size):
        if is_start[k]:
            x[:] = 0.0
        x = a_all[k] * x + (1.0 - a_all[k]) * prep.current_a[k]
        out[k] = x
    return out


def _hat_basis(soc: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Weights of the knot values in the OCV at each sample (``[n, K]``): linear
    interpolation between knots, and beyond the ends the straight line through the end
    value with the mean slope over :data:`service.cell.ocv.EXTRAPOLATION_SPAN`, as
    :class:`service.cell.ocv.OcvTable` reads the stored table."""
    def interp_rows(x: np.ndarray) -> np.ndarray:
        x = np.clip(x, knots[0], knots[-1])
        j = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, knots.size - 2)
        u = (x - knots[j]) / (knots[j + 1] - knots[j])
        rows = np.zeros((x.size, knots.size))
        idx = np.arange(x.size)
        rows[idx, j] = 1.0 - u
        rows[idx, j + 1] += u
        return rows

    basis = interp_rows(soc)
    lo_end, hi_end = knots[0], knots[-1]
    for outside, end, inner in ((soc < lo_end, lo_end, lo_end + EXTRAPOLATION_SPAN),
                                (soc > hi_end, hi_end, hi_end - EXTRAPOLATION_SPAN)):
        if not outside.any():
            continue
        e = (soc[outside] - end) / (end - inner)  # how many spans beyond the end, signed outwards
        at_end = interp_rows(np.full(e.size, end))
        at_inner = interp_rows(np.full(e.size, inner))
        basis[outside] = at_end * (1.0 + e[:, None]) - at_inner * e[:, None]
    return basis


def _triangular_factor(gram: np.ndarray) -> np.ndarray:
    """``R`` with ``RᵀR = gram``: the Cholesky factor of the augmented Gram matrix
    ``[A b]ᵀ W [A b]``, with a jitter far below the data's scale where a column is empty
    (and, should that still fail, the symmetric square root from its eigenvalues)."""
    jitter = 1e-12 * max(float(np.trace(gram)), 1e-12) / gram.shape[0]
    for _ in range(6):
        try:
            return np.linalg.cholesky(gram + jitter * np.eye(gram.shape[0])).T
        except np.linalg.LinAlgError:
            jitter *= 100.0
    lam, vec = np.linalg.eigh(gram)
    return np.sqrt(np.maximum(lam, 0.0))[:, None] * vec.T


def _bounded_lstsq(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, floor: float) -> np.ndarray:
    """``argmin ||a x - b||`` with ``lo ≤ x ≤ hi``.

    Every lower bound here is finite but the OCV level's, and the upper bounds are the
    resistances' ``r_max``, which a fit rarely reaches.  So the problem is first solved as
    non-negative least squares (:func:`scipy.optimize.nnls`, Lawson-Hanson, an order of
    magnitude faster than the general bounded solver) in ``y = x - lo`` with the level's
    bound at ``floor``; where that solution breaks an upper bound or sits on the stand-in
    floor, the general bounded solver (BVLS) solves the problem as posed."""
    lo_eff = np.where(np.isfinite(lo), lo, floor)
    try:
        y, _ = nnls(a, b - a @ lo_eff)
    except RuntimeError:  # iteration limit: leave it to the general solver
        y = None
    if y is not None:
        x = lo_eff + y
        on_floor = np.any((~np.isfinite(lo)) & (y <= 0.0))
        if not on_floor and np.all(x <= hi):
            return x
    return lsq_linear(a, b, bounds=(lo, hi), method="bvls", tol=1e-12).x


class _LinearProblem:
    """The bounded linear least-squares problem for fixed time constants.

    Unknowns: ``[R0, R1, R2]`` then, when the OCV is fitted, ``[level, d_1 .. d_{K-1}]``
    with the knot values ``v_j = level + Σ_{i ≤ j} d_i`` (``d ≥ 0``: monotone).  The OCV's
    columns are the sparse hat basis (at most three knots per sample) times the cumulative sum,
    so each Huber pass forms the normal equations in O(samples), not by stacking and multiplying
    a dense ``samples × knots`` matrix."""

    def __init__(self, prep: _Prepared, ocv_fixed: np.ndarray | None, knots: np.ndarray,
                 prior_v: np.ndarray | None, smooth_weight: float, prior_weight: float, r_max: float) -> None:
        self.prep = prep
        self.r_max = r_max
        self.rhs = prep.voltage_v - (ocv_fixed if ocv_fixed is not None else 0.0)
        #: a level no OCV of this recording goes below (the free OCV level's stand-in lower bound
        #: for the non-negative solver): 5 V under the lowest voltage measured
        self.level_floor = float(np.min(prep.voltage_v)) - 5.0
        n = prep.current_a.size
        k = 0 if ocv_fixed is not None else knots.size
        self.cum = np.tril(np.ones((k, k)))  # v = cum @ [level, d_1..]
        self.hat = sparse.csr_matrix(_hat_basis(prep.soc, knots)) if k else None
        self.pen_gram, self.pen_cross, self.pen_ss = np.zeros((k, k)), np.zeros(k), 0.0
        if k:
            # penalty rows: second differences of v (= first differences of d), scaled so the
            # penalty's weight grows with the data and does not depend on the knot count
            scale = math.sqrt(n / k)
            d2 = np.zeros((k - 2, k))
            for r in range(k - 2):
                d2[r, r:r + 3] = (1.0, -2.0, 1.0)
            pen = [smooth_weight * scale * (d2 @ self.cum)]
            pen_rhs = [np.zeros(k - 2)]
            if prior_v is not None and prior_weight > 0:
                pen.append(prior_weight * scale * self.cum)
                pen_rhs.append(prior_weight * scale * prior_v)
            rows, rows_rhs = np.vstack(pen), np.concatenate(pen_rhs)
            self.pen_gram, self.pen_cross, self.pen_ss = rows.T @ rows, rows.T @ rows_rhs, float(rows_rhs @ rows_rhs)

    @property
    def n_ocv(self) -> int:
        return self.cum.shape[0]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        k = self.n_ocv
        lo = np.concatenate([[0.0, 0.0, 0.0], [-np.inf] if k else [], np.zeros(max(k - 1, 0))])
        hi = np.concatenate([[self.r_max] * 3, [np.inf] if k else [], np.full(max(k - 1, 0), np.inf)])
        return lo, hi

    def gram(self, c: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``[A b]ᵀ W [A b]`` plus the penalty rows' own, with ``A = [c, hat·cum]`` (``c`` the
        resistances' columns) and ``W = diag(w)``: the last row and column are the right-hand side's."""
        cb = np.column_stack([c, self.rhs])
        wcb = cb * w[:, None]
        k, nc = self.n_ocv, c.shape[1]
        p = nc + k
        g = np.zeros((p + 1, p + 1))
        small = cb.T @ wcb
        idx = np.r_[0:nc, p]
        g[np.ix_(idx, idx)] = small
        if k:
            hat_t = self.hat.T
            g[nc:p, nc:p] = self.cum.T @ (hat_t @ self.hat.multiply(w[:, None])).toarray() @ self.cum + self.pen_gram
            cross = self.cum.T @ (hat_t @ wcb)
            cross[:, -1] += self.pen_cross
            g[nc:p, idx] = cross
            g[idx, nc:p] = cross.T
            g[p, p] += self.pen_ss
        return g

    def predict(self, c: np.ndarray, coef: np.ndarray) -> np.ndarray:
        """``A @ coef`` (without forming ``A``)."""
        out = c @ coef[:c.shape[1]]
        if self.n_ocv:
            out = out + self.hat @ (self.cum @ coef[c.shape[1]:])
        return out

    def solve(self, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Huber-weighted solution: ``(coefficients, residuals, robust cost)``."""
        c = -np.column_stack([self.prep.current_a, x1, x2])
        w = np.ones(self.rhs.size)
        lo, hi = self.bounds()
        p = lo.size
        for _ in range(HUBER_PASSES):
            # the tall problem compressed to its triangular factor: the same minimiser
            # (||A x - b||²_W = ||R x - Qᵀb||² + const) at a fraction of the cost
            tri = _triangular_factor(self.gram(c, w))
            coef = _bounded_lstsq(tri[:p, :p], tri[:p, p], lo, hi, self.level_floor)
            resid = self.rhs - self.predict(c, coef)
            scale = max(1.4826 * float(np.median(np.abs(resid - np.median(resid)))), 1e-4)
            u = np.abs(resid) / (HUBER_K * scale)
            w = np.where(u <= 1.0, 1.0, 1.0 / np.maximum(u, 1e-12))
        cut = HUBER_K * scale
        r = np.abs(resid)
        cost = float(np.sum(np.where(r <= cut, 0.5 * r**2, cut * r - 0.5 * cut**2)))
        return coef, resid, cost

    def knot_values(self, coef: np.ndarray) -> np.ndarray | None:
        if not self.n_ocv:
            return None
        return np.cumsum(coef[3:])


def fit_ecm2rc(
    segments: list[FitSegment],
    capacity_ah: float,
    *,
    ocv_soc: np.ndarray | None = None,
    ocv_v: np.ndarray | None = None,
    prior_v: np.ndarray | None = None,
    smooth_weight: float = OCV_SMOOTH_WEIGHT,
    prior_weight: float = 0.002,
) -> Ecm2RcFit:
    """Fit the textbook 2-RC model to ``segments`` (each starting relaxed, SOC0 known).

    With ``ocv_soc, ocv_v`` the OCV is that curve, held fixed; without, it is fitted on
    :data:`OCV_KNOTS` knots, monotone, smoothed by ``smooth_weight`` and pulled towards
    ``prior_v`` (values on the same knots) by ``prior_weight`` where the data is thin.
    """
    if not segments:
        raise ValueError("the 2-RC fit needs at least one segment")
    if not capacity_ah > 0:
        raise ValueError(f"capacity must be > 0, got {capacity_ah}")
    segments = select_segments(segments, MAX_FIT_SAMPLES)
    prep = _prepare(segments, capacity_ah)
    knots = np.linspace(0.0, 1.0, OCV_KNOTS)
    fixed = None
    if ocv_v is not None:
        if ocv_soc is None:
            raise ValueError("ocv_v needs ocv_soc")
        fixed = OcvTable.from_points(np.asarray(ocv_soc, dtype=float), np.asarray(ocv_v, dtype=float)).ocv(prep.soc, 25.0)
    prior = None if prior_v is None else np.asarray(prior_v, dtype=float)
    problem = _LinearProblem(prep, fixed, knots, prior, smooth_weight, prior_weight, r_max_ohm(capacity_ah))

    # candidate columns for the grid, computed once
    g1 = np.geomspace(*TAU1_BOUNDS_S, TAU_GRID_POINTS)
    g2 = np.geomspace(*TAU2_BOUNDS_S, TAU_GRID_POINTS)
    cols = branch_inputs(prep, np.concatenate([g1, g2]))
    best = (math.inf, g1[0], g2[-1])
    for a, t1 in enumerate(g1):
        for b, t2 in enumerate(g2):
            if t2 < MIN_TAU_RATIO * t1:
                continue
            _, _, cost = problem.solve(cols[:, a], cols[:, TAU_GRID_POINTS + b])
            if cost < best[0]:
                best = (cost, t1, t2)

    lo = np.log([TAU1_BOUNDS_S[0], TAU2_BOUNDS_S[0]])
    hi = np.log([TAU1_BOUNDS_S[1], TAU2_BOUNDS_S[1]])

    def objective(z: np.ndarray) -> float:
        t1, t2 = np.exp(np.clip(z, lo, hi))
        if t2 < MIN_TAU_RATIO * t1:
            return math.inf
        x = branch_inputs(prep, np.array([t1, t2]))
        return problem.solve(x[:, 0], x[:, 1])[2]

    z0 = np.log([best[1], best[2]])
    polish = minimize(objective, z0, method="Nelder-Mead", bounds=list(zip(lo, hi)),
                      options={"xatol": 0.02, "fatol": 1e-9, "maxfev": 40})
    z = polish.x if polish.fun <= best[0] else z0
    t1, t2 = (float(v) for v in np.exp(np.clip(z, lo, hi)))
    x = branch_inputs(prep, np.array([t1, t2]))
    coef, resid, _ = problem.solve(x[:, 0], x[:, 1])
    knot_v = problem.knot_values(coef)
    if knot_v is None:
        out_soc, out_v = np.asarray(ocv_soc, dtype=float), np.asarray(ocv_v, dtype=float)
    else:
        out_soc, out_v = knots, knot_v
    # the bounded solver can return -1e-18 for a resistance on its zero bound
    r0, r1, r2 = (max(float(c), 0.0) for c in coef[:3])
    return Ecm2RcFit(
        ocv_soc=out_soc, ocv_v=out_v, r0=r0, r1=r1, tau1_s=t1, r2=r2, tau2_s=t2, rmse_mv=1000.0 * float(np.sqrt(np.mean(resid**2))),
        n_samples=int(resid.size), r_max_ohm=problem.r_max,
    )


def simulate_ecm2rc(seg: FitSegment, capacity_ah: float, ocv_soc: np.ndarray, ocv_v: np.ndarray,
                    r0: float, r1: float, tau1_s: float, r2: float, tau2_s: float) -> np.ndarray:
    """Terminal voltage of the 2-RC model over ``seg`` (relaxed start, SOC from ``soc0``)."""
    prep = _prepare([seg], capacity_ah)
    x = branch_inputs(prep, np.array([tau1_s, tau2_s]))
    ocv = OcvTable.from_points(ocv_soc, ocv_v).ocv(prep.soc, 25.0)
    return ocv - r0 * prep.current_a - r1 * x[:, 0] - r2 * x[:, 1]
