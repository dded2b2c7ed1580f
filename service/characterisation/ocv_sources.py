"""Where an OCV(SOC) curve comes from: an OCV test, the rests of an HPPC test, or a
joint fit to a drive cycle when nothing better exists."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import median_filter
from scipy.optimize import least_squares

from service.cell.coulomb import coulomb_soc
from service.cell.ocv import GRID_POINTS, OcvTable, make_monotone
from service.cell.rests import REST_CURRENT_C, resting
from service.cell.units import SECONDS_PER_HOUR
from service.characterisation.ocv_choices import REST_INTERP_MAX_GAP
from service.recording import Recording

REST_MIN_S = 600.0
#: an OCV test's branches run at or below this fraction of 1C (C/20 is usual)
OCV_TEST_MAX_C = 0.1
#: a slow branch is one uninterrupted charge or discharge at or below OCV_TEST_MAX_C that moves at
#: least this fraction of the capacity (no drive cycle, HPPC or pulse test has one)
OCV_BRANCH_MIN_SPAN = 0.7
#: the slow branches are found on the current's running median over this many samples: a current
#: sensor's noise can be as large as a C/20 test current on a small cell (5 mA on a 0.17 Ah cell's
#: 8.5 mA), and single noisy samples outside the C/100..C/10 band must not cut the branch, while
#: a median keeps a constant-current step's edges where they are.  A sample further than twice
#: C/10 from that median is load, not noise, and still ends the branch (a drive cycle's current
#: can have a median within the band for a long time)
SLOW_MEDIAN_SAMPLES = 15


def slow_branches(rec: Recording, capacity_ah: float) -> list[tuple[float, np.ndarray]]:
    """``(sign, mask)`` of the slow branches of ``rec`` (sign +1 discharge, −1 charge): the longest
    uninterrupted run of same-sign current at or below :data:`OCV_TEST_MAX_C` for each sign (read
    on its running median, :data:`SLOW_MEDIAN_SAMPLES`), when it moves
    :data:`OCV_BRANCH_MIN_SPAN` of the capacity.  Faster parts of the file (a CC-CV charge
    before the test) and the tail of a constant-voltage phase (under a fifth of the branch's
    current) are not part of it."""
    dt = np.diff(rec.time_s, prepend=rec.time_s[0])
    level = median_filter(rec.current_a, size=SLOW_MEDIAN_SAMPLES, mode="nearest")
    abs_excursion = np.abs(rec.current_a - level)
    out = []
    for sign in (1.0, -1.0):
        i, lv = sign * rec.current_a, sign * level
        slow = (lv > REST_CURRENT_C * capacity_ah) & (lv <= OCV_TEST_MAX_C * capacity_ah)
        if not slow.any():
            continue
        slow &= (lv >= 0.2 * np.max(lv[slow])) & (abs_excursion <= 2 * OCV_TEST_MAX_C * capacity_ah)
        best, best_ah = None, 0.0
        for a, b in _runs(slow):
            ah = float(np.sum(i[a:b] * dt[a:b])) / SECONDS_PER_HOUR
            if ah > best_ah:
                best, best_ah = (a, b), ah
        if best is not None and best_ah >= OCV_BRANCH_MIN_SPAN * capacity_ah:
            mask = np.zeros(len(rec), dtype=bool)
            mask[best[0]:best[1]] = True
            out.append((sign, mask))
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` of every run of True in ``mask``."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2], edges[1::2]))


def is_ocv_test(rec: Recording, capacity_ah: float) -> bool:
    """A pseudo-OCV test: a slow (≤ C/10) charge or discharge over most of the capacity
    (:func:`slow_branches`), whatever else the file holds."""
    return bool(slow_branches(rec, capacity_ah)) and bool(np.ptp(rec.voltage_v) > 0.3)


#: the rest after an OCV test's charge is read this long after the charge ends (a longer rest
#: relaxes further; the rule below only needs it to have started)
POST_CHARGE_REST_S = 600.0


@dataclass
class OcvTestCurve:
    """An OCV test's curve on ``grid`` and how far its charge got: ``charge_reach`` is the charge's
    throughput over the discharge's when the charge stopped short of full (a cold C/20 charge
    reaches the voltage limit early), 1.0 when it reached full or the test has one branch;
    ``short_charge``: whether the curve counts such a charge on the discharge's scale."""

    grid: np.ndarray
    ocv_v: np.ndarray
    charge_reach: float = 1.0
    short_charge: bool = False
    #: the charge the test's slow discharge took out, else its one slow charge put in [Ah]
    branch_ah: float = float("nan")


@dataclass
class _Branch:
    q_ah: np.ndarray  # throughput counted from the branch's start
    voltage_v: np.ndarray
    first: int
    last: int


def _branch(rec: Recording, sign: float, mask: np.ndarray) -> _Branch:
    dt = np.diff(rec.time_s, prepend=rec.time_s[0])
    idx = np.flatnonzero(mask)
    q = np.cumsum(sign * rec.current_a[mask] * dt[mask]) / SECONDS_PER_HOUR
    return _Branch(q, rec.voltage_v[mask], int(idx[0]), int(idx[-1]))


def _on_grid(grid: np.ndarray, soc: np.ndarray, voltage_v: np.ndarray) -> np.ndarray:
    order = np.argsort(soc)
    return np.interp(grid, soc[order], make_monotone(voltage_v[order], 0.0))


def _charge_reach(rec: Recording, capacity_ah: float, dis: _Branch, chg: _Branch, grid: np.ndarray,
                  v_dis: np.ndarray, short_mean: np.ndarray) -> float:
    """Where a charge that returned less than the discharge took out ended, as a fraction of the
    discharge capacity: ``Q_chg / Q_dis`` when it stopped short of full, 1.0 when the counts only
    fail to close (coulombic loss, a current offset) and it did reach full.  ``v_dis``: the
    discharge branch on ``grid``; ``short_mean``: the branches' mean with the charge counted on the
    discharge's scale.

    The rest after the charge decides, without a threshold: stopped short, it rests near the
    branches' mean where the charge ended, counted on the discharge's scale; full, it rests near
    the voltage it rested at before the discharge.  A test that is not discharge-then-charge with
    a rest before and after is taken as reaching full."""
    rest = resting(rec.time_s, rec.current_a, capacity_ah)
    reach = float(chg.q_ah[-1] / dis.q_ah[-1])
    after = np.flatnonzero(rest & (rec.time_s > rec.time_s[chg.last])
                           & (rec.time_s <= rec.time_s[chg.last] + POST_CHARGE_REST_S))
    if reach >= 1.0 or dis.last > chg.first or dis.first == 0 or not rest[dis.first - 1] or not after.size:
        return 1.0
    v_full = rec.voltage_v[dis.first - 1]
    v_post = rec.voltage_v[after[-1]]
    implied = np.interp(reach, grid, v_dis) + _offset_at_reach(grid, reach, v_dis, short_mean)
    return reach if abs(v_post - implied) < abs(v_post - v_full) else 1.0


def ocv_from_test(rec: Recording, capacity_ah: float, grid: np.ndarray | None = None,
                  short_charge: bool = False) -> OcvTestCurve:
    """Average of the discharge and charge branches of a slow OCV test (:func:`slow_branches`).

    The discharge is coulomb counted from full (SOC = 1 − Q/Q_dis), the charge normalised by its
    own throughput (SOC = Q/Q_chg).  With ``short_charge``, a charge that stopped short of full
    (:func:`_charge_reach`) counts on the discharge's scale instead (SOC = Q/Q_dis), and above where
    it stopped the curve is the discharge branch raised by an offset that runs from the branches'
    mean offset there to the rested voltage at full.  That reads the test's OCV closer to the
    cell's, and scores worse pooled over the cells the defaults are chosen on (``socd fit
    --short-charge``, docs/results/tuning.md).  A single branch is used as it is.
    """
    grid = np.linspace(0, 1, GRID_POINTS) if grid is None else grid
    branches = {sign: _branch(rec, sign, mask) for sign, mask in slow_branches(rec, capacity_ah)}
    if not branches:
        raise ValueError(f"{rec.path}: no slow charge or discharge found for an OCV test")
    if len(branches) == 1:
        ((sign, b),) = branches.items()
        soc = 1.0 - b.q_ah / b.q_ah[-1] if sign > 0 else b.q_ah / b.q_ah[-1]
        return OcvTestCurve(grid, make_monotone(_on_grid(grid, soc, b.voltage_v)), branch_ah=float(b.q_ah[-1]))
    dis, chg = branches[1.0], branches[-1.0]
    v_dis = _on_grid(grid, 1.0 - dis.q_ah / dis.q_ah[-1], dis.voltage_v)
    short_mean = 0.5 * (v_dis + _on_grid(grid, chg.q_ah / dis.q_ah[-1], chg.voltage_v))
    reach = _charge_reach(rec, capacity_ah, dis, chg, grid, v_dis, short_mean)
    if short_charge and reach < 1.0:
        top = _above_reach(grid, reach, v_dis, short_mean, rec.voltage_v[dis.first - 1])
        return OcvTestCurve(grid, make_monotone(np.where(grid <= reach, short_mean, top)), reach, True,
                            float(dis.q_ah[-1]))
    mean = 0.5 * (v_dis + _on_grid(grid, chg.q_ah / chg.q_ah[-1], chg.voltage_v))
    return OcvTestCurve(grid, make_monotone(mean), reach, branch_ah=float(dis.q_ah[-1]))


#: a capacity more than this fraction above what a room-temperature OCV test's slow branch moved is
#: refused: a cell gives less charge at a drive's rates than at C/20, not more, so such a capacity is
#: a wrong number (SOC then drifts by the difference over every discharge). The margin is a tester's
#: counting error plus a charge that stops a little short of full.
CAPACITY_ABOVE_TEST_TOL = 0.05
#: above the test's charge by more than this (and up to the refusal) the fit log gives a notice: on
#: the PyBaMM cells each percent costs 0.1-0.4 points of SOC RMSE (research.fit_quality capacity)
CAPACITY_NOTICE_TOL = 0.01
#: the tests :func:`capacity_above_test` reads are within this many K of 25 °C (a cold test
#: gives less charge than the cell holds at room temperature)
ROOM_TEMPERATURE_SPAN_C = 10.0


@dataclass(frozen=True)
class CapacityAboveTest:
    """``--capacity-ah`` above the charge a room-temperature OCV test's slow branch moved."""

    text: str
    refused: bool


def capacity_above_test(name: str, curve: OcvTestCurve, temp_c: float, capacity_ah: float) -> CapacityAboveTest | None:
    """What to say when ``capacity_ah`` is more than :data:`CAPACITY_NOTICE_TOL` above the charge a
    room-temperature OCV test's slow branch moved (refused above :data:`CAPACITY_ABOVE_TEST_TOL`);
    None when it is not, or the test is not at room temperature."""
    if abs(temp_c - 25.0) > ROOM_TEMPERATURE_SPAN_C or not np.isfinite(curve.branch_ah):
        return None
    excess = capacity_ah / curve.branch_ah - 1.0
    if excess <= CAPACITY_NOTICE_TOL:
        return None
    return CapacityAboveTest(
        f"{name}: --capacity-ah {capacity_ah:g} is {excess:.1%} more than the {curve.branch_ah:.4g} Ah this OCV test's "
        f"slow branch moved at {temp_c:.0f} °C; a cell gives less at a drive's rates than at C/20, not more. Give the "
        f"capacity the cell delivers (e.g. --capacity-ah {curve.branch_ah:.4g})",
        refused=excess > CAPACITY_ABOVE_TEST_TOL)


#: the branches' mean offset where a short charge stopped is read over this SOC window below it
#: (its last few samples climb into the voltage limit)
REACH_WINDOW = (0.03, 0.005)


def _offset_at_reach(grid: np.ndarray, reach: float, v_dis: np.ndarray, mean: np.ndarray) -> float:
    """The branches' mean less the discharge branch just below ``reach`` (:data:`REACH_WINDOW`)."""
    window = (grid > reach - REACH_WINDOW[0]) & (grid < reach - REACH_WINDOW[1])
    return float(np.mean((mean - v_dis)[window])) if window.any() else float(np.interp(reach, grid, mean - v_dis))


def _above_reach(grid: np.ndarray, reach: float, v_dis: np.ndarray, mean: np.ndarray, v_full: float) -> np.ndarray:
    """The OCV above a short charge's end: the discharge branch plus an offset linear in SOC from
    the branches' mean offset at ``reach`` to the rested voltage at full."""
    at_reach = _offset_at_reach(grid, reach, v_dis, mean)
    at_full = v_full - v_dis[-1]
    return v_dis + at_reach + (at_full - at_reach) * (grid - reach) / (1.0 - reach)


#: how OCV rows are read beyond the OCV tests' temperatures (:func:`ocv_rows_by_temperature`)
OCV_BEYOND = ("hold", "linear")


def ocv_rows_by_temperature(tests: dict[float, np.ndarray], temps: list[float],
                            beyond: str = "hold") -> dict[float, np.ndarray]:
    """OCV rows at ``temps`` from OCV tests at their own temperatures (``tests``: temperature →
    row on one SOC grid): linear in temperature between tests; beyond them the nearest test's row
    (``hold``), or (``linear``, with two tests or more) the line through the two nearest, which
    carries their entropic slope dOCV/dT on (kept monotone in SOC)."""
    if beyond not in OCV_BEYOND:
        raise ValueError(f"OCV beyond the tests' temperatures: {beyond!r} is not one of {', '.join(OCV_BEYOND)}")
    known = sorted(tests)
    table = np.array([tests[t] for t in known])
    rows = {t: np.array([np.interp(t, known, col) for col in table.T]) for t in temps}
    if beyond == "linear" and len(known) >= 2:
        for t in temps:
            if known[0] <= t <= known[-1]:
                continue
            edge, other = (0, 1) if t < known[0] else (-1, -2)
            slope = (table[edge] - table[other]) / (known[edge] - known[other])
            rows[t] = make_monotone(table[edge] + slope * (t - known[edge]))
    return rows


@dataclass
class RestPoint:
    soc: float
    ocv_v: float
    temp_c: float
    #: how far the rest was from relaxed at its end, V (:func:`rest_reading`)
    unrelaxed_v: float = 0.0


#: :func:`relaxation_limit`: voltage means over this long a window at 1/3, 2/3 and the end of a rest
RELAX_WINDOW_S = 30.0
#: a last step below this is a settled rest (the end voltage is the limit)
RELAX_SETTLED_V = 0.3e-3
#: a step ratio at or above this (or not positive) is no clean first-order decay: the end voltage stands
RELAX_MAX_RATIO = 0.9


def rest_points(rec: Recording, capacity_ah: float, soc0: float = 1.0, min_rest_s: float = REST_MIN_S,
                extrapolate: bool = False) -> list[RestPoint]:
    """Relaxed voltages at the end of every rest of at least ``min_rest_s``; with ``extrapolate``,
    each rest's :func:`relaxation_limit` instead (a rest in the cold ends before it has relaxed).

    SOC at each rest from coulomb counting from ``soc0`` at the recording's first
    sample (backward zero-order hold, which matches the testers' Ah counters).
    """
    soc = coulomb_soc(rec.time_s, rec.current_a, capacity_ah, soc0)
    points = []
    for k, j in rest_spans(rec, capacity_ah, min_rest_s):
        limit, unrelaxed = rest_reading(rec.time_s[k:j + 1], rec.voltage_v[k:j + 1])
        points.append(RestPoint(float(soc[j]), limit if extrapolate else float(rec.voltage_v[j]),
                                float(rec.temperature_c[j]), unrelaxed))
    return points


def relaxation_limit(time_s: np.ndarray, voltage_v: np.ndarray) -> float:
    """The voltage a rest relaxes towards, by Aitken's Δ² on a first-order decay
    ``v(t) = v∞ + a·exp(-t/τ)``: at three equally spaced times the steps ``d1, d2`` shrink by
    ``r = d2/d1 = exp(-Δt/τ)``, so ``v∞ = v3 + d2·r/(1-r)``.  The three voltages are window means
    (:data:`RELAX_WINDOW_S`) at a third, two thirds and the end of the rest.  A settled rest
    (:data:`RELAX_SETTLED_V`) or steps that do not shrink geometrically (:data:`RELAX_MAX_RATIO`)
    give the end voltage."""
    return rest_reading(time_s, voltage_v)[0]


def rest_reading(time_s: np.ndarray, voltage_v: np.ndarray) -> tuple[float, float]:
    """``(limit, unrelaxed)``: :func:`relaxation_limit`, and how far the rest was from it at its end:
    the limit minus the end voltage where the decay was extrapolated, the last step ``d2`` where it
    could not be (a decay slower than first order: the rest is still moving by that much), 0 where
    it had settled."""
    t, v = np.asarray(time_s, dtype=float), np.asarray(voltage_v, dtype=float)
    means = []
    for frac in (1.0 / 3.0, 2.0 / 3.0, 1.0):
        tc = t[0] + frac * (t[-1] - t[0])
        window = (t >= tc - RELAX_WINDOW_S) & (t <= tc)
        means.append(float(v[window].mean()) if window.any() else float(np.interp(tc, t, v)))
    d1, d2 = means[1] - means[0], means[2] - means[1]
    if abs(d2) < RELAX_SETTLED_V or d1 == 0.0:
        return float(v[-1]), 0.0
    ratio = d2 / d1
    if not 0.0 < ratio < RELAX_MAX_RATIO:
        return float(v[-1]), d2
    return float(v[-1] + d2 * ratio / (1.0 - ratio)), d2 * ratio / (1.0 - ratio)


def rest_spans(rec: Recording, capacity_ah: float, min_rest_s: float) -> list[tuple[int, int]]:
    """``(first, last)`` sample of every rest (:func:`resting`) lasting ``min_rest_s``."""
    return [(int(a), int(b) - 1) for a, b in _runs(resting(rec.time_s, rec.current_a, capacity_ah))
            if rec.time_s[b - 1] - rec.time_s[a] >= min_rest_s]


#: rests spanning at least this much counted SOC fix the OCV curve's SOC scale (:func:`soc_alignment`)
ALIGN_MIN_SPAN = 0.5
#: the alignment's bounds: the recording's counted charge within ±10 % of the OCV curve's scale, and
#: its full point within 0.1 of the curve's
ALIGN_SCALE_BOUNDS = (0.9, 1.1)
ALIGN_SHIFT_BOUND = 0.1


def soc_alignment(base_soc: np.ndarray, base_ocv: np.ndarray, soc: np.ndarray, ocv_v: np.ndarray) -> tuple[float, float]:
    """``(shift, scale)`` of the map SOC_curve = shift + scale · (SOC_counted − 1) + 1 that puts relaxed
    rest voltages (at coulomb-counted ``soc``) best on the OCV curve, with a free common voltage offset.

    An OCV test normalises SOC by its own throughput down to its cut-off; a recording counts with the
    profile's capacity from its own full point. Where the two scales differ by a few per cent, a
    voltage offset between them grows without bound towards empty (the curve is steep there), so the
    scale is aligned first and only what is left is treated as an offset. Beyond [0, 1] the curve is
    read as a stored table is (:meth:`service.cell.ocv.OcvTable.ocv`)."""
    table = OcvTable.from_points(base_soc, base_ocv)

    def residual(x: np.ndarray) -> np.ndarray:
        r = ocv_v - table.ocv(x[0] + x[1] * (soc - 1.0) + 1.0)
        return r - np.mean(r)
    lo, hi = ALIGN_SCALE_BOUNDS
    fit = least_squares(residual, [0.0, 1.0], bounds=([-ALIGN_SHIFT_BOUND, lo], [ALIGN_SHIFT_BOUND, hi]))
    return float(fit.x[0]), float(fit.x[1])


def usable_rests(points: list[RestPoint]) -> list[RestPoint]:
    """Rest points at a plausible counted SOC, in SOC order."""
    return sorted((p for p in points if -0.02 <= p.soc <= 1.02), key=lambda p: p.soc)


def rest_alignment(base_soc: np.ndarray, base_ocv: np.ndarray, points: list[RestPoint]) -> tuple[float, float] | None:
    """:func:`soc_alignment` of the usable rest points, or ``None`` where they span less than
    :data:`ALIGN_MIN_SPAN` (too little SOC to fix a scale)."""
    pts = usable_rests(points)
    s = np.array([p.soc for p in pts])
    if s.size < 2 or np.ptp(s) < ALIGN_MIN_SPAN:
        return None
    return soc_alignment(base_soc, base_ocv, s, np.array([p.ocv_v for p in pts]))


def alignment_at_bound(alignment: tuple[float, float]) -> bool:
    """True when :func:`soc_alignment` ended on one of its bounds (a capacity or a full point far
    from the OCV curve's: a wrong ``--capacity-ah`` or full-charge point, more often than a cell)."""
    shift, scale = alignment
    lo, hi = ALIGN_SCALE_BOUNDS
    return abs(shift) >= 0.999 * ALIGN_SHIFT_BOUND or scale <= lo * 1.001 or scale >= hi * 0.999


def ocv_row_from_rests(base_soc: np.ndarray, base_ocv: np.ndarray, points: list[RestPoint],
                       min_points: int = 3) -> np.ndarray:
    """Base curve, its SOC scale aligned to the rest points where they span
    :data:`ALIGN_MIN_SPAN` (:func:`rest_alignment`), then shifted by the (smoothly interpolated)
    voltage offset of the rest points; beyond the outermost points the outermost offset holds.
    Fewer than ``min_points``: unchanged."""
    pts = usable_rests(points)
    if len(pts) < max(min_points, 1):
        return base_ocv
    s = np.array([p.soc for p in pts])
    v = np.array([p.ocv_v for p in pts])
    alignment = rest_alignment(base_soc, base_ocv, pts)
    if alignment is not None:
        shift, scale = alignment
        base_ocv = OcvTable.from_points(base_soc, base_ocv).ocv(shift + scale * (base_soc - 1.0) + 1.0)
    off = v - np.interp(s, base_soc, base_ocv)
    return make_monotone(base_ocv + np.interp(base_soc, s, off))


#: rests closer than this in counted SOC are one reading of the OCV there (their mean)
REST_MERGE_SOC = 0.005
#: a temperature's rests have settled when the median of how far each was from relaxed at its end
#: (:func:`rest_reading`) is within this: they are then readings of the OCV, not extrapolations
#: towards it (a cold rest ends far from its limit, a slow one still moving)
REST_SETTLED_V = 1e-3


def rests_settled(points: list[RestPoint]) -> bool:
    """True when the median remaining relaxation of the usable ``points`` is within
    :data:`REST_SETTLED_V`."""
    usable = usable_rests(points)
    return bool(usable) and float(np.median([abs(p.unrelaxed_v) for p in usable])) <= REST_SETTLED_V


def merged_rests(points: list[RestPoint]) -> tuple[np.ndarray, np.ndarray]:
    """``(soc, ocv_v)`` of the usable rest points, those within :data:`REST_MERGE_SOC` of a group's
    first merged into their mean, in SOC order."""
    groups: list[list[RestPoint]] = []
    for p in usable_rests(points):
        if groups and p.soc - groups[-1][0].soc < REST_MERGE_SOC:
            groups[-1].append(p)
        else:
            groups.append([p])
    return (np.array([np.mean([p.soc for p in g]) for g in groups]),
            np.array([np.mean([p.ocv_v for p in g]) for g in groups]))


def interpolate_between_rests(base_soc: np.ndarray, row: np.ndarray, points: list[RestPoint]) -> np.ndarray:
    """``row`` (an OCV row already through the rests, :func:`ocv_row_from_rests`) with the stretch
    between every two neighbouring rests (:func:`merged_rests`) no more than
    :data:`REST_INTERP_MAX_GAP` apart replaced by the monotone cubic (PCHIP) through them.

    A jointly fitted OCV is pinned by the rests only where they are; between them its shape is what
    the spline's knots made of the dynamic data, and on a pulse test it wiggles by tens of mV between
    steps 10 % apart.  A relaxed rest is a direct reading of the OCV, and an OCV curve is smooth on
    that scale, so between close rests the rests decide.  Across a wider gap, and beyond the
    outermost rests, the row is kept."""
    soc, ocv = merged_rests(points)
    if soc.size < 2:
        return row
    out = row.copy()
    curve = PchipInterpolator(soc, ocv, extrapolate=False)
    for lo, hi in pairwise(soc):
        if hi - lo <= REST_INTERP_MAX_GAP:
            inside = (base_soc >= lo) & (base_soc <= hi)
            out[inside] = curve(base_soc[inside])
    return make_monotone(out)
