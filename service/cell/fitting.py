"""Fit the base MTS-FOM parameters (Zeng Fig. 1) to recorded voltage.

Shared by ``socd fit`` (characterise a cell) and ``socd diagnose`` (fit the base model
before naming what it misses).  The model fitted is :class:`service.cell.model.MtsFom`
itself, run through :func:`service.cell.trajectory.simulate_batch` with ``N`` parameter
candidates at once, so what is fitted is exactly what the estimator runs.

Search space (all bounded, physical)::

    ln R_ohm, ln R_ct, ln tau_ct, m, ln R_df, ln(tau_df / tau_ct), n  [, U_H, ln rate]

A CPE branch is parametrised by its resistance and its characteristic time
``tau = (R C)^(1/alpha)`` rather than by ``C``: the voltage response scales with ``R``
at fixed ``tau``, which decouples the coordinates, and ``tau_df = tau_ct * ratio`` with
``ratio >= 3`` keeps the charge-transfer branch the fast one (no label switching).
``C = tau^alpha / R``.  ``m, n`` are kept in [0.3, 1].

Procedure:

1. global search: :func:`scipy.optimize.differential_evolution` (seeded, vectorised
   over the population, time-bounded) on a full-rate window of at most
   ``global_points`` samples per segment (:func:`excited_window`);
2. local polish: :func:`scipy.optimize.least_squares` (``trf``, bounds) on the data at
   full rate (windowed to at most ``polish_points`` samples for very long recordings,
   e.g. Panasonic HPPC ~100k rows).  Its Jacobian is a forward difference evaluated as
   one vectorised simulation of ``p + 1`` candidates.

Why windows and not a subsampled grid: the short-memory G-L step (Zeng Eq. 2) keeps
``L`` *samples* of history, so the model's response depends on the sampling period;
parameters fitted on a coarser grid do not transfer to the rate the estimator runs at
(a fit on a block-averaged grid that matches that grid well can miss the same recording
at full rate).  The fit therefore always runs at the recording's rate.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import differential_evolution, least_squares

from service.cell.model import DEFAULT_MEMORY_LENGTH
from service.cell.profile import (
    CellParameters,
    CellProfile,
    HysteresisSpec,
    ParameterPoint,
    lift_to_ohmic_floor,
    ln_cpe_tau,
    ohmic_floor_ohm,
)
from service.cell.temperature_law import scaled_by_law, temperature_law_factor
from service.cell.trajectory import simulate_batch
from service.cell.units import SECONDS_PER_HOUR

#: bounds of the search coordinates (see module docstring)
BOUNDS: dict[str, tuple[float, float]] = {
    "ln_r_ohm": (math.log(1e-4), math.log(1.0)),
    "ln_r_ct": (math.log(1e-5), math.log(1.0)),
    "ln_tau_ct": (math.log(0.1), math.log(300.0)),
    "m": (0.3, 1.0),
    "ln_r_df": (math.log(1e-5), math.log(2.0)),
    "ln_tau_ratio": (math.log(3.0), math.log(3000.0)),
    "n": (0.3, 1.0),
}
HYSTERESIS_BOUNDS: dict[str, tuple[float, float]] = {
    "u_h_max_v": (0.0, 0.15),
    "ln_rate": (math.log(1.0), math.log(1000.0)),
}
#: Butler-Volmer exchange current (``--kinetics``): from strongly non-linear (0.05 A) to
#: practically linear over a cell's currents (500 A)
KINETICS_BOUNDS: dict[str, tuple[float, float]] = {"ln_i0_a": (math.log(0.05), math.log(500.0))}
#: the exchange current of a point whose Butler-Volmer term is practically linear (the bound above)
LINEAR_I0_A = math.exp(KINETICS_BOUNDS["ln_i0_a"][1])
#: activation energy of the resistances within a fit (``temperature_law``), kJ/mol: none to
#: well above what electrolyte conduction, charge transfer and solid diffusion show (20-80)
TEMPERATURE_LAW_BOUNDS: dict[str, tuple[float, float]] = {"ea_kj_mol": (0.0, 120.0)}
#: the fit re-reads a candidate's parameters when the temperature has moved this far [K]
LAW_UPDATE_K = 0.5
BASE_NAMES = tuple(BOUNDS)
#: the bounds above are for a cell of at least this capacity: the cells they were set on ran from
#: 0.87 Ah (PyBaMM's Marquis2019) to 5.1 Ah.  A smaller cell has proportionally larger resistances
#: and smaller currents (a 0.17 Ah cell's charge transfer at 0 °C is over 1 Ω, and a strongly
#: non-linear exchange current under 0.05 A), so :func:`search_bounds` and :func:`kinetics_bounds`
#: widen them by the ratio.
BOUNDS_MIN_CAPACITY_AH = 0.85
#: the resistance coordinates, whose upper bounds scale as 1 / capacity below it
RESISTANCE_NAMES = ("ln_r_ohm", "ln_r_ct", "ln_r_df")


def small_cell_ratio(capacity_ah: float) -> float:
    """How many times smaller than :data:`BOUNDS_MIN_CAPACITY_AH` a cell is (1 for a cell that size or larger)."""
    return max(1.0, BOUNDS_MIN_CAPACITY_AH / capacity_ah) if capacity_ah > 0 else 1.0


def search_bounds(capacity_ah: float) -> dict[str, tuple[float, float]]:
    """:data:`BOUNDS` for a cell of ``capacity_ah`` (same coordinates, same order): below
    :data:`BOUNDS_MIN_CAPACITY_AH` the resistances' upper bounds rise by the cell's
    :func:`small_cell_ratio`, so the search spans the same range of resistance x capacity as on the
    cells the bounds were set on.  Times and orders do not scale with size."""
    widen = math.log(small_cell_ratio(capacity_ah))
    return {k: ((lo, hi + widen) if k in RESISTANCE_NAMES else (lo, hi)) for k, (lo, hi) in BOUNDS.items()}


def kinetics_bounds(capacity_ah: float) -> dict[str, tuple[float, float]]:
    """:data:`KINETICS_BOUNDS` for a cell of ``capacity_ah``: below :data:`BOUNDS_MIN_CAPACITY_AH`
    the exchange current's lower bound falls by the cell's :func:`small_cell_ratio` (the same range
    in C); its upper, practically linear end (:data:`LINEAR_I0_A`) does not move."""
    lo, hi = KINETICS_BOUNDS["ln_i0_a"]
    return {"ln_i0_a": (lo - math.log(small_cell_ratio(capacity_ah)), hi)}


@dataclass
class FitSegment:
    """One stretch of recording to fit, with its known starting state."""

    time_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray
    temperature_c: np.ndarray
    soc0: float
    u_h0: float = 0.0
    #: the starting U_h in units of the candidate's U_H (+1 just after a charge, -1 after
    #: a discharge); added to ``u_h0``, so a fit of the hysteresis starts on the right branch
    u_h0_branch: float = 0.0

    def __post_init__(self) -> None:
        self.time_s = np.asarray(self.time_s, dtype=float)
        self.current_a = np.asarray(self.current_a, dtype=float)
        self.voltage_v = np.asarray(self.voltage_v, dtype=float)
        self.temperature_c = np.asarray(self.temperature_c, dtype=float)
        n = self.time_s.size
        for name in ("current_a", "voltage_v", "temperature_c"):
            if getattr(self, name).size != n:
                raise ValueError(f"FitSegment.{name} has {getattr(self, name).size} samples, time_s has {n}")
        if n < 3:
            raise ValueError(f"FitSegment needs at least 3 samples, has {n}")
        if np.any(np.diff(self.time_s) <= 0):
            raise ValueError("FitSegment.time_s must increase strictly")

    def __len__(self) -> int:
        return int(self.time_s.size)


@dataclass
class FitResult:
    point: ParameterPoint
    hysteresis: HysteresisSpec | None
    rmse_mv: float
    n_evaluations: int
    #: the search coordinates that ended on a bound (:func:`coordinates_at_bounds`)
    at_bounds: list[str] = field(default_factory=list)
    #: wall time of the search, and whether it was cut by ``max_seconds`` (its end point then
    #: depends on the machine's speed and load) rather than ending by its own criteria
    seconds: float = 0.0
    time_bound: bool = False
    #: the resistances' activation energy [J/mol] the point was fitted with (``temperature_law``),
    #: else None; the point is then the parameters at its own ``temp_c``
    ea_j_mol: float | None = None
    #: the Butler-Volmer exchange current ended on its lower bound (the most non-linear the search
    #: allows): the data asked for more curvature than the term may give, so the term absorbed
    #: something it does not model rather than measuring i0
    i0_at_lower_bound: bool = False


# -- data helpers -------------------------------------------------------------------------
def decimate(seg: FitSegment, max_points: int) -> FitSegment:
    """Block-average ``seg`` to at most ``max_points`` samples.

    Current is averaged over each block (charge, hence SOC, is preserved under the
    model's backward zero-order hold); voltage and temperature are block means, which
    pair with the mean current in the ohmic term.  Time is the block's last stamp.
    """
    n = len(seg)
    k = max(1, math.ceil(n / max_points))
    if k == 1:
        return seg
    # the first sample is kept on its own: it carries the initial state's time stamp
    t0 = seg.time_s[:1]
    rest = n - 1
    m = rest // k
    if m < 2:
        return seg
    start = n - m * k  # drop a few samples right after the first so blocks tile the tail
    dt = np.diff(seg.time_s)[start - 1:]  # interval before each sample in the tail
    sl = slice(start, None)

    def block_mean(x: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        x = x[sl].reshape(m, k)
        if w is None:
            return x.mean(axis=1)
        w = w.reshape(m, k)
        return (x * w).sum(axis=1) / w.sum(axis=1)

    # the dropped samples' charge goes into the first block
    i_first = seg.current_a[1:start]
    dt_first = np.diff(seg.time_s)[: start - 1]
    cur = block_mean(seg.current_a, dt)
    if i_first.size:
        w0 = dt[:k].sum()
        cur[0] = (cur[0] * w0 + float((i_first * dt_first).sum())) / (w0 + dt_first.sum())
    return FitSegment(
        time_s=np.concatenate([t0, seg.time_s[sl].reshape(m, k)[:, -1]]),
        current_a=np.concatenate([seg.current_a[:1], cur]),
        voltage_v=np.concatenate([seg.voltage_v[:1], block_mean(seg.voltage_v)]),
        temperature_c=np.concatenate([seg.temperature_c[:1], block_mean(seg.temperature_c)]),
        soc0=seg.soc0,
        u_h0=seg.u_h0,
        u_h0_branch=seg.u_h0_branch,
    )


def excited_window(seg: FitSegment, max_points: int, capacity_ah: float) -> FitSegment:
    """A full-rate window of at most ``max_points`` samples with the most current variation.

    Windows start at the segment's start or at the end of a rest (so the CPE branches
    are near zero); the window's SOC0 is coulomb-counted from the segment's.  Hysteresis
    state is carried only by a window at the segment's start.
    """
    n = len(seg)
    if n <= max_points:
        return seg
    rest = np.abs(seg.current_a) < 0.01 * capacity_ah
    ends = np.flatnonzero(rest[:-1] & ~rest[1:]) + 1
    starts = np.unique(np.concatenate([[0], ends[ends <= n - max_points]]))
    if starts.size > 200:
        starts = starts[np.linspace(0, starts.size - 1, 200).astype(int)]
    csum = np.concatenate([[0.0], np.cumsum(seg.current_a)])
    csq = np.concatenate([[0.0], np.cumsum(seg.current_a**2)])
    var = (csq[starts + max_points] - csq[starts]) / max_points - ((csum[starts + max_points] - csum[starts]) / max_points) ** 2
    a = int(starts[int(np.argmax(var))])
    dt = np.diff(seg.time_s, prepend=seg.time_s[0])
    soc_a = seg.soc0 - float(np.sum(seg.current_a[1:a + 1] * dt[1:a + 1])) / (SECONDS_PER_HOUR * capacity_ah)
    sl = slice(a, a + max_points)
    # a segment that tracks its hysteresis branch (u_h0_branch != 0) hands it on to a later window
    branch = seg.u_h0_branch
    if a > 0 and branch != 0.0:
        branch = last_current_direction(seg.current_a[1:a + 1], 0.01 * capacity_ah) or branch
    return FitSegment(seg.time_s[sl], seg.current_a[sl], seg.voltage_v[sl], seg.temperature_c[sl], soc0=soc_a,
                      u_h0=seg.u_h0 if a == 0 else 0.0, u_h0_branch=branch)


def last_current_direction(current_a: np.ndarray, rest_a: float) -> float:
    """+1 if the last current above ``rest_a`` was a charge, -1 a discharge, 0 if none.

    The hysteresis branch a segment starts on: Zeng Eq. 1 drives ``U_h`` to ``-sgn(I)·U_H``
    and a rest does not move it, so after the charge throughput of a typical drive step it
    is near the bound of the last direction (an approximation: a short last step leaves it
    part-way)."""
    moving = np.flatnonzero(np.abs(current_a) > rest_a)
    if moving.size == 0:
        return 0.0
    return float(-np.sign(current_a[moving[-1]]))


def estimate_r_ohm(segments: list[FitSegment]) -> float | None:
    """Median instantaneous resistance ``-dV/dI`` over large current steps (first guess)."""
    vals = []
    for s in segments:
        di = np.diff(s.current_a)
        dv = np.diff(s.voltage_v)
        big = np.abs(di) > max(0.2 * np.max(np.abs(s.current_a)), 1e-3)
        if big.any():
            vals.append(-dv[big] / di[big])
    if not vals:
        return None
    r = float(np.median(np.concatenate(vals)))
    return r if r > 0 else None


# -- parameter coding ---------------------------------------------------------------------
def decode(x: np.ndarray, profile: CellProfile, temp_c: float, fit_hysteresis: bool,
           fit_kinetics: bool = False, max_tau_df_s: float | None = None,
           min_pure_ohm: float = 0.0) -> CellParameters:
    """Search coordinates ``x[N, p]`` -> :class:`CellParameters` for ``N`` candidates.

    Coordinates: the 7 base ones, then ``U_H, ln rate`` (``fit_hysteresis``), then
    ``ln i0`` (``fit_kinetics``, the Butler-Volmer term of :func:`kinetic_overpotential`).
    ``max_tau_df_s`` caps the diffusion branch's time constant (:func:`diffusion_tau`).
    ``min_pure_ohm``: the least ``R_ohm`` above the Butler-Volmer term's linear drop
    (:func:`service.cell.profile.ohmic_floor_ohm`).
    """
    x = np.atleast_2d(x)
    n = x.shape[0]
    base = profile.parameters_at(temp_c, n_cells=n)
    r_ohm = np.exp(x[:, 0])
    r_ct, tau_ct, m = np.exp(x[:, 1]), np.exp(x[:, 2]), x[:, 3]
    r_df, tau_df, nn = np.exp(x[:, 4]), diffusion_tau(x[:, 2] + x[:, 5], max_tau_df_s), x[:, 6]
    r = np.array(base.r, copy=True)
    c = np.array(base.c, copy=True)
    alpha = np.array(base.alpha, copy=True)
    r[:, 0], r[:, 1] = r_ct, r_df
    alpha[:, 0], alpha[:, 1] = m, nn
    c[:, 0] = tau_ct**m / r_ct
    c[:, 1] = tau_df**nn / r_df
    p = CellParameters(
        r_ohm=r_ohm, r=r, c=c, alpha=alpha, u_h_max=base.u_h_max, hyst_rate=base.hyst_rate,
        capacity_ah=base.capacity_ah, current_bias_a=base.current_bias_a, kinetics_i0_a=base.kinetics_i0_a,
    )
    if fit_hysteresis:
        p.u_h_max = x[:, 7].copy()
        p.hyst_rate = np.exp(x[:, 8])
    if fit_kinetics:
        p.kinetics_i0_a = np.exp(x[:, 9 if fit_hysteresis else 7])
    # R_ohm holds the Butler-Volmer term's linear drop (CellProfile rejects less) and a pure ohmic part
    i0 = p.kinetics_i0_a if fit_kinetics else None
    p.r_ohm = np.maximum(p.r_ohm, ohmic_floor_ohm(i0, temp_c, profile.min_r_ohm_scale(temp_c), min_pure_ohm))
    return p


def diffusion_tau(ln_tau: np.ndarray | float, max_tau_s: float | None) -> np.ndarray:
    """The diffusion branch's time constant from its log, capped at ``max_tau_s``: a branch
    slower than the recordings it is fitted to acts as an integrator that absorbs OCV and
    capacity error instead of describing the cell (``socd fit`` caps it; diagnose does not)."""
    tau = np.exp(ln_tau)
    return tau if max_tau_s is None else np.minimum(tau, max_tau_s)


def encode_point(point: ParameterPoint, capacity_ah: float = BOUNDS_MIN_CAPACITY_AH) -> np.ndarray:
    """A :class:`ParameterPoint` -> base search coordinates (clipped into the bounds of a cell of
    ``capacity_ah``, :func:`search_bounds`)."""
    ln_tau_ct = ln_cpe_tau(point.r_ct, point.c_dl, point.m)
    ln_tau_df = ln_cpe_tau(point.r_df, point.c_df, point.n)
    x = np.array([
        math.log(point.r_ohm), math.log(point.r_ct), ln_tau_ct, point.m,
        math.log(point.r_df), max(ln_tau_df - ln_tau_ct, math.log(1e-12)), point.n,
    ])
    lo, hi = np.array(list(search_bounds(capacity_ah).values())).T
    return np.clip(x, lo, hi)


def point_from_x(x: np.ndarray, temp_c: float, i0_a: float | None = None,
                 max_tau_df_s: float | None = None) -> ParameterPoint:
    r_ct, tau_ct, m = math.exp(x[1]), math.exp(x[2]), float(x[3])
    r_df, tau_df, n = math.exp(x[4]), float(diffusion_tau(x[2] + x[5], max_tau_df_s)), float(x[6])
    return ParameterPoint(
        temp_c=float(temp_c), r_ohm=math.exp(x[0]), r_ct=r_ct, c_dl=tau_ct**m / r_ct, m=min(m, 1.0),
        r_df=r_df, c_df=tau_df**n / r_df, n=min(n, 1.0), i0_a=i0_a,
    )


# -- the objective ------------------------------------------------------------------------
class _Objective:
    """Residuals of ``N`` candidates over all segments, one vectorised simulation each."""

    def __init__(self, profile, segments, memory_length, fit_hysteresis, temp_c, fit_kinetics=False,
                 max_tau_df_s=None, temperature_law=False, min_pure_ohm=0.0):
        self.max_tau_df_s = max_tau_df_s
        self.min_pure_ohm = min_pure_ohm
        #: the last coordinate is the resistances' activation energy [kJ/mol]: each sample is
        #: simulated with the candidate scaled from ``temp_c`` to its own temperature
        self.temperature_law = temperature_law
        self.profile = profile
        self.segments = segments
        self.memory_length = memory_length
        self.fit_hysteresis = fit_hysteresis
        self.fit_kinetics = fit_kinetics
        self.temp_c = temp_c
        self.n_evaluations = 0
        self.n_samples = sum(len(s) for s in segments)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """``[N, samples]`` simulated minus measured voltage."""
        x = np.atleast_2d(x)
        params = decode(x, self.profile, self.temp_c, self.fit_hysteresis, self.fit_kinetics, self.max_tau_df_s,
                        self.min_pure_ohm)
        law = None
        if self.temperature_law:
            ea = 1000.0 * x[:, -1]

            def law(t: float) -> CellParameters:
                return scaled_by_law(params, temperature_law_factor(ea, t, self.temp_c))
        out = []
        for s in self.segments:
            v, _ = simulate_batch(
                self.profile, s.time_s, s.current_a, s.temperature_c, s.soc0, params,
                memory_length=self.memory_length, u_h0=s.u_h0, u_h0_branch=s.u_h0_branch,
                params_at=law, temp_update_k=LAW_UPDATE_K,
            )
            out.append(v.T - s.voltage_v[None, :])
        self.n_evaluations += x.shape[0]
        res = np.concatenate(out, axis=1)
        return np.where(np.isfinite(res), np.clip(res, -10.0, 10.0), 10.0)


class _Deadline(Exception):
    pass


def fit_parameters(
    profile: CellProfile,
    segments: list[FitSegment],
    *,
    memory_length: int = DEFAULT_MEMORY_LENGTH,
    fit_hysteresis: bool = False,
    fit_kinetics: bool = False,
    max_seconds: float = 120.0,
    seed: int = 0,
    global_points: int = 1200,
    polish_points: int = 20000,
    x0: ParameterPoint | None = None,
    de_maxiter: int = 200,
    warmer: ParameterPoint | None = None,
    colder: ParameterPoint | None = None,
    min_order: float | None = None,
    max_tau_df_s: float | None = None,
    temperature_law: bool = False,
    law_ref_temp_c: float | None = None,
    pinned: dict[str, float] | None = None,
    min_slow_order: float | None = None,
    min_pure_ohm: float = 0.0,
) -> FitResult:
    """Fit R_ohm, R_ct, C_dl, m, R_df, C_df, n (and U_H, rate; and the Butler-Volmer i0) to ``segments``.

    ``profile`` supplies the OCV, capacity and extensions (kept as they are); its
    parameters are only a template.  ``x0`` (a point) seeds the search.  The global
    stage gets about 60 % of ``max_seconds`` or ``de_maxiter`` generations, whichever
    ends first (set ``de_maxiter`` for a result that does not depend on machine load);
    the polish gets the rest of the time.

    ``min_order`` raises the lower bound of the CPE orders ``m, n`` (default 0.3).  With the
    short G-L memory (L = 16 samples) the truncated tail of the weights grows as the order
    falls (|w_j| ~ j^(-1-α)), so a low-order branch fitted at one rate is mostly truncation.
    ``min_slow_order`` raises the lower bound of the diffusion branch's order ``n`` alone: that
    branch's time constant is tens of times the memory, so truncation is worst there.

    ``max_tau_df_s`` caps the diffusion branch's time constant (:func:`diffusion_tau`).

    ``min_pure_ohm`` [Ω]: ``R_ohm`` keeps at least this much above the Butler-Volmer term's linear
    drop (:func:`service.cell.profile.ohmic_floor_ohm`), so the search cannot hand the electrolyte's
    and contacts' resistance to the kinetic term.

    ``temperature_law``: also fit an activation energy ``Ea`` of the resistances
    (:mod:`service.cell.temperature_law`), so each sample is simulated with the point scaled
    from the point's temperature to its own; the point is then the parameters at that
    temperature, not a compromise over the span (a drive cycle in the cold warms the cell
    by 10-20 K, and the resistances halve on the way).  ``Ea`` is returned beside the point.
    ``law_ref_temp_c``: the temperature the point is for (default, and always without the
    law: the segments' mean).

    ``pinned``: base coordinates (names of :data:`BOUNDS`) held at the values given instead of
    searched, e.g. the CPE orders of the reference temperature's point (``socd fit --shape``).

    ``warmer`` / ``colder``: points already fitted at a warmer / colder temperature.  The
    three resistances are then bounded to be at least the warmer point's and at most the
    colder point's (electrolyte conduction, charge transfer and solid diffusion all slow
    down in the cold: Arrhenius with positive activation energies).  Without this, each
    temperature trades R_ohm, R_ct and R_df against one another freely and the
    temperature interpolation between two good fits can be a poor model (a colder fit may
    come out with R_ohm below a warmer one).
    """
    if not segments:
        raise ValueError("fit_parameters needs at least one segment")
    t_start = time.perf_counter()
    deadline = t_start + max_seconds
    total = sum(len(s) for s in segments)
    temp_c = float(np.average([np.mean(s.temperature_c) for s in segments], weights=[len(s) for s in segments]))
    if temperature_law and law_ref_temp_c is not None:
        temp_c = float(law_ref_temp_c)

    cell_bounds = search_bounds(profile.effective_capacity_ah)
    base_bounds = dict(cell_bounds)
    for name, bound in (("min_order", min_order), ("min_slow_order", min_slow_order)):
        if bound is not None and not 0.0 < bound < 1.0:
            raise ValueError(f"{name} must be in (0, 1), got {bound}")
    if min_order is not None:
        base_bounds["m"] = (min_order, 1.0)
        base_bounds["n"] = (min_order, 1.0)
    if min_slow_order is not None:
        base_bounds["n"] = (max(base_bounds["n"][0], min_slow_order), 1.0)
    for key, attr in (("ln_r_ohm", "r_ohm"), ("ln_r_ct", "r_ct"), ("ln_r_df", "r_df")):
        lo_b, hi_b = base_bounds[key]
        if warmer is not None:
            lo_b = max(lo_b, math.log(getattr(warmer, attr)))
        if colder is not None:
            hi_b = min(hi_b, math.log(getattr(colder, attr)))
        if hi_b <= lo_b:
            hi_b = lo_b + 1e-6
        base_bounds[key] = (lo_b, hi_b)
    for key, value in (pinned or {}).items():
        base_bounds[key] = pinned_bounds(value, *cell_bounds[key])
    extra_bounds = ((HYSTERESIS_BOUNDS if fit_hysteresis else {})
                    | (kinetics_bounds(profile.effective_capacity_ah) if fit_kinetics else {})
                    | (TEMPERATURE_LAW_BOUNDS if temperature_law else {}))
    bounds = list(base_bounds.values()) + list(extra_bounds.values())
    lo, hi = np.array(bounds).T
    p = len(bounds)

    # a first guess: the seed point, else R_ohm from current steps and mid-range dynamics
    if x0 is not None:
        guess = encode_point(x0, profile.effective_capacity_ah)
    else:
        r0 = estimate_r_ohm(segments) or 0.02
        guess = np.array([math.log(r0), math.log(r0 / 2), math.log(5.0), 0.8, math.log(r0), math.log(40.0), 0.8])
    if fit_hysteresis:
        guess = np.concatenate([guess, [0.01, math.log(30.0)]])
    if fit_kinetics:
        i0_seed = x0.i0_a if x0 is not None and x0.i0_a is not None else 5.0
        guess = np.concatenate([guess, [math.log(i0_seed)]])
    if temperature_law:  # the seed as it is: the same parameters at every temperature
        guess = np.concatenate([guess, [0.0]])
    for key, value in (pinned or {}).items():
        guess[BASE_NAMES.index(key)] = value
    guess = np.clip(guess, lo + 1e-9, hi - 1e-9)

    # 1. global search on full-rate windows
    cap = profile.effective_capacity_ah
    coarse = [excited_window(s, max(200, int(global_points * len(s) / total)), cap) for s in segments]
    obj_g = _Objective(profile, coarse, memory_length, fit_hysteresis, temp_c, fit_kinetics, max_tau_df_s,
                       temperature_law, min_pure_ohm)
    g_deadline = t_start + 0.6 * max_seconds

    def cost(xt: np.ndarray) -> np.ndarray:  # xt: [p, S] (vectorised DE)
        r = obj_g.residuals(xt.T)
        return np.mean(r**2, axis=1)

    cut = {"global": False, "polish": False}

    def stop(intermediate_result) -> bool:  # scipy passes the result by this name
        cut["global"] = time.perf_counter() > g_deadline
        return cut["global"]

    de = differential_evolution(
        cost, bounds, seed=seed, popsize=max(6, 60 // p), maxiter=de_maxiter, tol=1e-4, mutation=(0.5, 1.0),
        recombination=0.8, polish=False, vectorized=True, updating="deferred", x0=guess, callback=stop,
        init="sobol",
    )
    x_best = np.clip(de.x, lo, hi)

    # 2. local polish on (nearly) full-rate data
    fine = [excited_window(s, max(200, int(polish_points * len(s) / total)), cap) for s in segments]
    obj = _Objective(profile, fine, memory_length, fit_hysteresis, temp_c, fit_kinetics, max_tau_df_s,
                     temperature_law, min_pure_ohm)
    steps = np.full(p, 1e-4)
    best = {"x": x_best, "cost": np.inf}
    cache: dict[str, np.ndarray] = {}

    def fun(x: np.ndarray) -> np.ndarray:
        key = x.tobytes()
        if key in cache:
            r = cache[key]
        else:
            if time.perf_counter() > deadline:
                raise _Deadline
            r = obj.residuals(x)[0]
        c = float(r @ r)
        if c < best["cost"]:
            best.update(x=x.copy(), cost=c)
        return r

    def jac(x: np.ndarray) -> np.ndarray:
        if time.perf_counter() > deadline:
            raise _Deadline
        h = steps * np.where(x + steps > hi, -1.0, 1.0)
        xs = np.vstack([x, x + np.diag(h)])
        r = obj.residuals(xs)
        cache.clear()
        cache[x.tobytes()] = r[0]
        return ((r[1:] - r[0]) / h[:, None]).T

    try:
        least_squares(fun, np.clip(x_best, lo + 1e-9, hi - 1e-9), jac=jac, bounds=(lo, hi), method="trf",
                      x_scale="jac", max_nfev=60, xtol=1e-6, ftol=1e-7)
    except _Deadline:
        cut["polish"] = True
    x_fin = best["x"] if np.isfinite(best["cost"]) else x_best
    if not np.isfinite(best["cost"]):
        best["cost"] = float(np.sum(obj.residuals(x_fin)[0] ** 2))
    rmse_mv = 1000.0 * math.sqrt(best["cost"] / obj.n_samples)
    hyst = None
    if fit_hysteresis:
        hyst = profile.hysteresis.model_copy(update={"u_h_max_v": float(max(x_fin[7], 0.0)),
                                                     "rate": float(math.exp(x_fin[8]))})
    names = list(base_bounds) + list(extra_bounds)
    i0 = float(math.exp(x_fin[names.index("ln_i0_a")])) if fit_kinetics else None
    ea = 1000.0 * float(x_fin[names.index("ea_kj_mol")]) if temperature_law else None
    # R_ohm as decode() simulated it
    point = lift_to_ohmic_floor(point_from_x(x_fin, temp_c, i0, max_tau_df_s), i0, profile.min_r_ohm_scale(temp_c),
                                min_pure_ohm)
    hits = coordinates_at_bounds(x_fin, names, lo, hi)
    return FitResult(
        point=point,
        hysteresis=hyst,
        rmse_mv=rmse_mv,
        n_evaluations=obj_g.n_evaluations + obj.n_evaluations,
        # an activation energy of 0 is a finding (no measurable change), not a degenerate fit
        # a pinned coordinate sits on its own narrow range by design
        at_bounds=[text for name, edge, text in hits
                   if name not in (pinned or {}) and not (name == "ea_kj_mol" and edge == "lower")],
        i0_at_lower_bound=any(name == "ln_i0_a" and edge == "lower" for name, edge, _ in hits),
        seconds=time.perf_counter() - t_start,
        time_bound=cut["global"] or cut["polish"],
        ea_j_mol=ea,
    )


#: width of the range a pinned coordinate is searched over: the optimisers need a non-empty one
PINNED_WIDTH = 1e-6


def pinned_bounds(value: float, lo: float, hi: float) -> tuple[float, float]:
    """A range of :data:`PINNED_WIDTH` holding ``value`` (clipped into ``lo..hi``)."""
    a = min(max(value - PINNED_WIDTH / 2, lo), hi - PINNED_WIDTH)
    return a, a + PINNED_WIDTH


def coordinates_at_bounds(x: np.ndarray, names: list[str], lo: np.ndarray, hi: np.ndarray,
                          rel: float = 1e-3) -> list[tuple[str, str, str]]:
    """``(name, "lower" | "upper", "name = value (lower|upper bound)")`` for every search coordinate
    within ``rel`` of the width of its range from a bound (log coordinates shown as their value)."""
    out = []
    for name, v, a, b in zip(names, x, lo, hi):
        edge = "lower" if v <= a + rel * (b - a) else "upper" if v >= b - rel * (b - a) else None
        if edge is None:
            continue
        shown = f"{name[3:]} = {math.exp(v):.4g}" if name.startswith("ln_") else f"{name} = {v:.3g}"
        out.append((name, edge, f"{shown} ({edge} bound)"))
    return out
