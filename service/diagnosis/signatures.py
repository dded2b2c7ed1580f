"""Effect-specific signatures that a generic model error cannot fake.

A held-out gain alone does not name physics: a flexible extension (an OCV correction,
Butler–Volmer kinetics, an Arrhenius law) also soaks up the mismatch between the
estimator's equivalent-circuit model and any real (or physics-simulated) cell, so a clean
recording shows gains too.  A signature is evidence *outside* the voltage fit that the
departure the effect describes is present.  An effect whose signature fires is
*nominated* and is then confirmed on the held-out part with a lower gain bar
(:class:`service.diagnosis.pipeline.DiagnoseOptions`); the others need the full bar.

* ``temperature`` — the effect is a changing **ambient** (a cold start that warms, a warm
  cell that cools).  Self-heating alone is explained by a first-order thermal model with
  a constant ambient, ``τ dT/dt = T_amb + a (I/C)² - T``.  Its fit to the recorded
  temperature (RMS misfit, K) is a few tenths of a kelvin with self-heating only and
  degrees when the ambient moves; the voltage never enters.  An ambient that moves
  *smoothly* from a cold or warm start is the same first-order lag as a cell that opens
  away from a constant ambient, so the misfit misses it; the second statistic is the
  **opening temperature** (median of the first :data:`OPENING_WINDOW_S`): a cell at rest
  sits at its ambient, so one that opens :data:`OPENING_TEMP_K` or more from the nominal
  ambient (:data:`NOMINAL_AMBIENT_C`, the ``--nominal-ambient-c`` of ``socd diagnose``)
  and whose temperature then moves by :data:`TEMP_RANGE_K` or more is in an ambient that
  is not the nominal one.  The third is the **coldest temperature** (1st percentile): a cell
  heats itself but cannot cool below its ambient, so one that falls :data:`OPENING_TEMP_K`
  or more below the nominal ambient (a warm start that cools, an ambient that drops) sits in
  a colder one.  A fitted constant ambient would say the same but is extrapolated when the
  lag is long (a real 25 °C drive that warms 4 K fits an ambient of −10 °C), so it is not
  read.  A recording at a constant temperature is never nominated by these.
* ``current_bias`` — in a rest the true current is exactly zero, so the mean of the
  *measured* current over rest samples is the sensor offset itself (:func:`rest_current_offset`).
  Rests are runs of at least :data:`REST_MIN_SAMPLES` samples with ``|I| < REST_MAX_C · C``
  (3 % of 1C: above any offset worth naming, so a biased rest is still a rest; where the
  sensor's noise crosses that level, its running mean, :func:`service.cell.rests.resting`) whose
  current is *constant* (robust spread within :data:`REST_SPREAD_FACTOR` of the pooled
  rest noise) and whose level agrees with the other rests (a trickle or a low load step is
  not a rest).  The offset's standard error is corrected for autocorrelation
  (``σ·sqrt(τ_int/n)``).  Nominated when ``|z| >= BIAS_MIN_Z`` (5: not a noise
  fluctuation) **and** the Coulomb-count drift it causes over the recording,
  ``|b|·duration / C``, is at least :data:`BIAS_MIN_DRIFT_SOC` (0.1 % SOC) **and** ``|b|``
  is at least :data:`BIAS_MIN_FRAC_1C` of the 1C current (0.05 %, a current-sensor
  accuracy scale): large enough to matter to an estimator.  Spikes inside a rest (beyond
  :data:`REST_OUTLIER_SIGMA` pooled σ of the rest's median) are left out.  This is a direct measurement, not a pattern in a fit, so the
  pipeline treats it as such (see :mod:`service.diagnosis.pipeline`).
* ``capacity`` — the classic two-point capacity check: the charge drawn between two
  points whose SOC the OCV table gives, over the SOC difference (:func:`two_point_capacity`).
  Capacity is defined between ``v_min`` and ``v_max`` at equilibrium, so the ends of the
  OCV curve anchor SOC for any cell, aged or not; the points are the opening rest (at least
  :data:`CAPACITY_MIN_OPENING_REST_S`; a recording that opens under load is not checked) and
  the end (in the last :data:`CAPACITY_END_WINDOW_S`, the end of the latest rest of at least
  :data:`RELAX_REST_MIN_S`, else the latest rest sample, else the lightest load there: a final rest,
  or the approach to a cut-off).  Under load the OCV there is the
  voltage minus the base model's overpotential ``η``; the model may be wrong, so the OCV is taken only to
  lie between ``V − η_Ω`` and ``V − η_Ω − 2(η − η_Ω)``, where ``η_Ω = −R_Ω·I`` is the
  ohmic drop (``R_Ω`` identified from the fit part's voltage steps) and the model's
  polarisation ``η − η_Ω`` may be off by up to 100 %.  At the end of a rest of at least
  :data:`RELAX_REST_MIN_S` the rest's own relaxation bounds it instead (the voltage, and twice the
  relaxation still to come read as a diffusion tail): there the model's polarisation is an
  extrapolation of the fit part, on a cell that has run to its cut-off tens of mV off.  Either
  interval is widened by :data:`CAPACITY_OCV_FLOOR_V` (hysteresis, relaxation, table error).  Nominated, as a
  direct measurement, when the whole resulting capacity interval lies at least
  :data:`CAPACITY_MIN_ERROR` from the stated capacity and the points are at least
  :data:`CAPACITY_MIN_SPAN` of SOC apart; a flat OCV (LFP) widens the interval by itself.
* ``hysteresis`` — at the end of a long rest (at least :data:`BRANCH_REST_MIN_S`) the voltage
  stands for the OCV of the branch the cell is on, and the user's table is the mean of the
  branches (:func:`rest_branch_offset`).  The rest-end voltages are fitted, with the model
  left out, by ``OCV(s0 − q_k) + U_H·h_k``: ``q_k`` the charge drawn (Coulomb count over the
  stated capacity), ``h_k`` the Eq.-1 direction state (−1 after discharge, +1 after charge;
  rate from a small grid) and ``s0`` free, so an initial SOC read off a branch is not taken
  for an offset; the varying OCV slope separates ``s0`` from ``U_H`` even when every rest
  follows a discharge.  Nominated, as a direct measurement of the half-gap, when at least
  :data:`BRANCH_MIN_RESTS` rests give ``U_H`` of the physical sign (the discharge branch lies
  below the table) with ``z >= BRANCH_MIN_Z``, at least :data:`BRANCH_MIN_HALF_GAP_V`, the
  rests agree with one constant half-gap (residual spread at most
  :data:`BRANCH_MAX_SPREAD` of ``U_H``: a wrong capacity or OCV curve leaves an offset that
  changes with SOC) and they have finished relaxing (the relaxation left at the rest ends,
  extrapolated from their last quarter as ``2·t·dV/dt``, at most :data:`BRANCH_MAX_RELAXATION`
  × ``U_H``: a slow diffusion leaves every post-discharge rest low too).  A recording without
  such rests (a drive cycle) has no signature here.
  A drive cycle without such rests has a second, model-based test (:func:`direction_offset`):
  the base model's residual over the fit part, high-passed (a :data:`DIRECTION_HIGHPASS_S`
  moving mean removed, so slow SOC-dependent misfit drops out), is regressed on the C-rate, its
  low-passes at 10-1000 s (any linear polarisation the base model got wrong) and the Eq.-1
  direction state (rate from :data:`BRANCH_RATES`, best fit).  What the direction state explains
  beyond every linear filter of the current is the saturating, sign-only part that hysteresis
  is.  Nominated (not measured: the 10 % bar) when its coefficient is a half-gap of at least
  :data:`BRANCH_MIN_HALF_GAP_V` of the physical sign with ``z >= DIRECTION_MIN_Z``
  (autocorrelation-corrected).
* ``kinetics`` — slow charge transfer is an overpotential that appears within a second of a
  current change and is non-linear in the current: the apparent resistance falls as the
  current rises (Butler–Volmer, ``η = (2RT/F)·asinh(I/(2·i0))``).  :func:`step_kinetics`
  reads the voltage change across every current step between two samples (at least
  :data:`STEP_MIN_C` × 1C, the current steady in the sample before and the one after: a
  step table, a pulse), where neither the OCV nor a slower branch has time to move, and fits
  ``ΔV = −R·ΔI − (2RT/F)·[asinh(c₂/2x) − asinh(c₁/2x)]`` with ``c`` the C-rates before and after
  and ``x = i0`` in C.  Everything linear (ohmic drop, the first second of a fast RC branch)
  goes into ``R``; only the curvature fixes ``x``.  Nominated when at least
  :data:`STEP_MIN_STEPS` steps reach :data:`STEP_MIN_PEAK_C` and the upper end of the
  two-sided 95 % interval of ``x`` lies below the healthy-cell bound
  :data:`service.diagnosis.effects.KINETICS_MAX_I0_C` (the bound the kinetics extension's
  own fitted size must meet).  Only the fit part's steps are read.
* ``diffusion`` — a slow solid diffusion shows as relaxation that is still running at the end
  of a long rest (:func:`rest_relaxation`).  For each rest of at least
  :data:`RELAX_REST_MIN_S` after a load step of at least :data:`RELAX_MIN_STEP_C` × 1C, the
  relaxation still to come is extrapolated from the rest's last quarter as a diffusion tail
  (``V∞ − V ∝ t^−1/2``, so ``V∞ − V(t) = 2·t·dV/dt``) and divided by the instantaneous
  voltage step when the current stopped (the ohmic drop, which every cell shows at once).  A
  healthy Li-ion cell has done nearly all of its relaxing after ten minutes; nominated when the
  median ratio is at least :data:`RELAX_MIN_RATIO` and the pooled z of the remaining
  relaxation is at least :data:`RELAX_MIN_Z`.  It nominates (the lower gain bar), it does not
  measure the extension's size: how much of the slow relaxation the surface lag describes is
  left to the held-out score.  From a median ratio of :data:`RELAX_DIRECT_RATIO` it measures the
  departure directly (the held-out voltage then only has to agree).  The pipeline passes only the
  fit part's rests, so no held-out voltage enters it.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.optimize import least_squares

from service.cell.current_steps import (
    STEP_MIN_C,
    STEP_MIN_PEAK_C,
    STEP_MIN_STEPS,
    current_steps,
    steps_peak_c,
    steps_resolve_kinetics,
)
from service.cell.profile import kinetic_voltage_v
from service.cell.rests import resting
from service.cell.units import SECONDS_PER_HOUR
from service.characterisation.relaxation import rc_voltage
from service.diagnosis.effects import KINETICS_MAX_I0_C
from service.diagnosis.features import direction_state, lowpass

#: RMS misfit of the constant-ambient thermal model above which the ambient is taken to move
AMBIENT_DRIFT_K = 0.5
#: the nominal ambient a recording is judged against (the synthetic data's definition of a
#: nominal recording: 25 °C ambient with normal cooling)
NOMINAL_AMBIENT_C = 25.0
#: the opening temperature: median over this long from the first sample
OPENING_WINDOW_S = 60.0
#: an opening this far from the nominal ambient (beyond the few K a cell keeps after a charge) ...
OPENING_TEMP_K = 5.0
#: ... nominates ``temperature`` when the temperature also moves this much (else nothing to model)
TEMP_RANGE_K = 2.0
#: rest detection: |I| below this multiple of the 1C current ...
REST_MAX_C = 0.03
#: ... for at least this many consecutive samples
REST_MIN_SAMPLES = 10
#: samples dropped at each end of a rest run (a step may straddle a sample)
REST_EDGE_SAMPLES = 2
#: a run's robust current spread must stay below this multiple of the pooled rest noise
REST_SPREAD_FACTOR = 3.0
#: offset z-score (autocorrelation-corrected) needed to nominate current_bias
BIAS_MIN_Z = 5.0
#: Coulomb-count drift over the recording (fraction of SOC) needed to nominate current_bias
BIAS_MIN_DRIFT_SOC = 0.001
#: and the offset as a fraction of the 1C current (a sensor-accuracy scale)
BIAS_MIN_FRAC_1C = 5e-4
#: rest samples further than this many pooled noise σ from their run's median are spikes
REST_OUTLIER_SIGMA = 6.0
#: two-point capacity: OCV uncertainty added at each point besides the overpotential (hysteresis,
#: unfinished relaxation, OCV-table error of a few mV to ~10 mV in Li-ion cells)
CAPACITY_OCV_FLOOR_V = 0.010
#: the capacity interval must clear the stated capacity by this fraction to nominate (a capacity
#: error below ~2 % is within what a BMS capacity estimate resolves)
CAPACITY_MIN_ERROR = 0.02
#: and the two points must lie this far apart in SOC
CAPACITY_MIN_SPAN = 0.3
#: the end point is the sample of least current within this window before the recording's end
CAPACITY_END_WINDOW_S = 300.0
#: hysteresis: rests at least this long stand for the branch OCV at their end (GITT/HPPC practice)
BRANCH_REST_MIN_S = 600.0
#: ... and at least this many such rests (besides the opening one, whose branch is unknown)
BRANCH_MIN_RESTS = 4
#: z of the half-gap (standard error from the rests' residual spread) needed to nominate
BRANCH_MIN_Z = 5.0
#: a half-gap below this is within what an OCV table is good for
BRANCH_MIN_HALF_GAP_V = 0.004
#: rest residual spread (RMS, V) as a share of the half-gap: more and the offset is not one branch gap
BRANCH_MAX_SPREAD = 0.12
#: relaxation still to come at the rest ends, as a multiple of the half-gap
BRANCH_MAX_RELAXATION = 1.5
#: direction-state rates tried (Eq. 1, per unit SOC throughput)
BRANCH_RATES = (10.0, 30.0, 100.0, 300.0)
#: hysteresis on drive cycles: the residual and regressors are high-passed by a moving mean this long
DIRECTION_HIGHPASS_S = 600.0
#: ... low-passes of the C-rate that stand for any linear polarisation the base model got wrong
DIRECTION_LOWPASS_S = (10.0, 30.0, 100.0, 300.0, 1000.0)
#: z of the direction-state coefficient needed to nominate hysteresis: model-form error alone
#: also gives a recording without hysteresis some z, so the bar sits above what such recordings
#: of the PyBaMM stand-in (``research.validate_pybamm``) reach, at the cost of the weakest
#: hysteresis ones (docs/results/diagnose.md)
DIRECTION_MIN_Z = 8.0
#: diffusion: rests at least this long (a final 600 s rest counts after its trimmed edges) ...
#: (``python -m research.devset rules --search-rest-length`` reads shorter ones: the development set
#: gains one verdict at 120 s, the own-model grid loses most of its diffusion lags; docs/results/diagnose.md)
RELAX_REST_MIN_S = 500.0
#: ... after a load step of at least this C-rate (so the ohmic step is measured well)
RELAX_MIN_STEP_C = 0.2
#: relaxation still to come at the rest end over the ohmic step: nominates diffusion above this
RELAX_MIN_RATIO = 0.15
#: pooled z of the remaining relaxation needed besides
RELAX_MIN_Z = 5.0
#: ... and at this ratio (with the same z) the relaxation *measures* slow diffusion directly: the
#: surface lag then only has to agree with the held-out voltage, not improve it (a base model whose
#: slow branch stretches to hours describes the relaxation as well as the lag does, and the held-out
#: gain that decides a nominated effect is not there).  ``math.inf``: never (chosen leave-one-cell-out,
#: ``python -m research.devset rules``)
RELAX_DIRECT_RATIO = math.inf
#: the opening point must be a rest at least this long (a recording that opens under load has
#: no OCV-anchored start)
CAPACITY_MIN_OPENING_REST_S = 30.0


def _thermal_sim(th: np.ndarray, time_s: np.ndarray, load: np.ndarray, t0: float) -> np.ndarray:
    """First-order lag ``τ dT/dt = T_amb + a·load − T`` from ``T = t0``: the RC step of
    :func:`service.characterisation.relaxation.rc_voltage` applied to ``T − t0``."""
    t_amb, ln_a, ln_tau = th
    a, tau = math.exp(ln_a), math.exp(ln_tau)
    return t0 + rc_voltage(time_s, t_amb + a * load - t0, 1.0, tau)


def ambient_drift_k(time_s: np.ndarray, current_a: np.ndarray, temperature_c: np.ndarray, capacity_ah: float,
                    max_points: int = 1500) -> dict:
    """RMS misfit (K) of the constant-ambient self-heating model to the recorded temperature.

    The current is reduced to ``(I/C)²`` block means (heat is ∝ I²), the temperature to
    block means, on at most ``max_points`` blocks.
    """
    n = time_s.size
    k = max(1, math.ceil(n / max_points))
    m = n // k
    if m < 10:
        return {"rms_k": 0.0, "max_k": 0.0, "range_k": 0.0, "t_amb_c": float(temperature_c[0])}
    sl = slice(0, m * k)
    load = ((current_a[sl] / capacity_ah) ** 2).reshape(m, k).mean(axis=1)
    temp = temperature_c[sl].reshape(m, k).mean(axis=1)
    t = time_s[sl].reshape(m, k)[:, -1]
    span = max(float(t[-1] - t[0]), 60.0)
    best = None
    for tau0 in (0.05 * span, 0.2 * span, 0.8 * span):
        x0 = [float(temp[0]), 0.0, math.log(max(tau0, 30.0))]
        try:
            sol = least_squares(lambda th: _thermal_sim(th, t, load, float(temp[0])) - temp, x0,
                                bounds=([-60.0, -10.0, math.log(30.0)], [120.0, 8.0, math.log(max(10 * span, 300.0))]),
                                max_nfev=200)
        except ValueError:
            continue
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None:
        return {"rms_k": 0.0, "max_k": 0.0, "range_k": 0.0, "t_amb_c": float(temp[0])}
    res = best.fun
    return {"rms_k": float(np.sqrt(np.mean(res**2))), "max_k": float(np.max(np.abs(res))),
            "range_k": float(temp.max() - temp.min()), "t_amb_c": float(best.x[0])}


def _runs(mask: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    """``[start, stop)`` of the runs of True in ``mask`` at least ``min_len`` long."""
    m = np.concatenate([[False], mask.astype(bool), [False]])
    d = np.diff(m.astype(np.int8))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops) if b - a >= min_len]


def _robust_sd(x: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def integrated_autocorr_time(r: np.ndarray, max_lag: int = 400) -> float:
    """``1 + 2 Σ ρ_k`` up to the first lag with ``ρ < 0.05``: how many samples one independent
    sample is worth (used for effective sample counts and standard errors)."""
    x = r - r.mean()
    var = float(x @ x)
    if var == 0:
        return 1.0
    tau = 1.0
    for lag in range(1, min(max_lag, x.size // 4)):
        rho = float(x[:-lag] @ x[lag:]) / var
        if rho < 0.05:
            break
        tau += 2.0 * rho
    return tau


def rest_runs(time_s: np.ndarray, current_a: np.ndarray, capacity_ah: float) -> list[tuple[int, int]]:
    """Rests: near-zero, constant-current runs whose level agrees with the other rests.

    Returns ``[start, stop)`` index pairs with :data:`REST_EDGE_SAMPLES` trimmed at each end.
    """
    near = resting(time_s, current_a, capacity_ah, REST_MAX_C)
    runs = [(a + REST_EDGE_SAMPLES, b - REST_EDGE_SAMPLES)
            for a, b in _runs(near, REST_MIN_SAMPLES + 2 * REST_EDGE_SAMPLES)]
    if not runs:
        return []
    spreads = np.array([_robust_sd(current_a[a:b]) for a, b in runs])
    noise = max(float(np.median(spreads)), 1e-4)
    runs = [r for r, sd in zip(runs, spreads) if sd <= REST_SPREAD_FACTOR * noise]
    if not runs:
        return []
    # a common level: runs whose median sits far from the median of run medians are not rests
    meds = np.array([np.median(current_a[a:b]) for a, b in runs])
    lens = np.array([b - a for a, b in runs])
    centre = float(np.median(np.repeat(meds, lens)))
    tol = 5.0 * noise / np.sqrt(lens) + 1e-3 * capacity_ah
    return [r for r, m, t in zip(runs, meds, tol) if abs(m - centre) <= t]


def _rest_samples(current_a: np.ndarray, runs: list[tuple[int, int]]) -> list[np.ndarray]:
    """Per rest, its current samples without spikes (beyond REST_OUTLIER_SIGMA pooled σ of its median)."""
    noise = max(float(np.median([_robust_sd(current_a[a:b]) for a, b in runs])), 1e-4)
    out = []
    for a, b in runs:
        x = current_a[a:b]
        keep = np.abs(x - np.median(x)) <= REST_OUTLIER_SIGMA * noise
        if keep.sum() >= 3:
            out.append(x[keep])
    return out


def rest_current_offset(time_s: np.ndarray, current_a: np.ndarray, capacity_ah: float) -> dict:
    """Current-sensor offset measured in rests (true current 0): mean, SE, z, drift."""
    runs = rest_runs(time_s, current_a, capacity_ah)
    duration_h = float(time_s[-1] - time_s[0]) / SECONDS_PER_HOUR
    out = {"nominated": False, "direct": True, "statistic": 0.0, "offset_a": 0.0, "se_a": None, "n_rest_samples": 0,
           "n_rests": len(runs), "drift_soc": 0.0, "what": "z-score of the mean measured current in rests "
           "(true current 0), autocorrelation-corrected", "threshold": BIAS_MIN_Z,
           "min_drift_soc": BIAS_MIN_DRIFT_SOC}
    if not runs:
        return out
    per_rest = _rest_samples(current_a, runs)
    if not per_rest:
        return out
    vals = np.concatenate(per_rest)
    n = vals.size
    mean = float(vals.mean())
    # autocorrelation inside runs (pooled deviations from each run's own mean)
    dev = np.concatenate([x - x.mean() for x in per_rest])
    tau = integrated_autocorr_time(dev, max_lag=200)
    sd = float(vals.std(ddof=1)) if n > 1 else 0.0
    if sd == 0.0:  # quantised to exact zeros: only the resolution bounds the offset
        diffs = np.abs(np.diff(np.unique(current_a)))
        sd = float(diffs[diffs > 0].min()) / math.sqrt(12.0) if np.any(diffs > 0) else 1e-6
    se = sd * math.sqrt(tau / n)
    z = mean / se if se > 0 else 0.0
    drift = abs(mean) * duration_h / capacity_ah
    # agreement between rests (one constant offset): chi-square per degree of freedom
    run_means = np.array([x.mean() for x in per_rest])
    run_se = np.array([sd * math.sqrt(tau / x.size) for x in per_rest])
    chi2 = float(np.mean(((run_means - mean) / run_se) ** 2)) if len(per_rest) > 1 else float("nan")
    frac = abs(mean) / capacity_ah
    out.update(nominated=bool(abs(z) >= BIAS_MIN_Z and drift >= BIAS_MIN_DRIFT_SOC and frac >= BIAS_MIN_FRAC_1C),
               statistic=round(abs(z), 2), offset_frac_1c=round(mean / capacity_ah, 6), min_frac_1c=BIAS_MIN_FRAC_1C,
               offset_a=mean, se_a=se, n_rest_samples=int(n), drift_soc=round(drift, 5), tau_int=round(tau, 2),
               rest_seconds=round(float(sum(time_s[b - 1] - time_s[a] for a, b in runs)), 1),
               chi2_per_rest=None if not np.isfinite(chi2) else round(chi2, 2))
    return out


def _soc_interval(table, v: float, eta: float, temp_c: float, ohmic_v: float = 0.0) -> tuple[float, float, float]:
    """SOC (lo, point, hi) at a point with voltage ``v`` and model overpotential ``eta``.

    ``ohmic_v`` is the ohmic part of ``eta`` (``-R_ohm·I``); the rest, the model's
    polarisation, may be off by up to 100 %.
    """
    ocv = v - eta
    dyn = eta - ohmic_v
    ends = (v - ohmic_v, v - ohmic_v - 2.0 * dyn)
    soc = table.soc_from_ocv(np.array([min(ends) - CAPACITY_OCV_FLOOR_V, ocv, max(ends) + CAPACITY_OCV_FLOOR_V]),
                             temp_c)
    return float(soc[0]), float(soc[1]), float(soc[2])


def _last_load(rest: np.ndarray) -> np.ndarray:
    """For each sample, the index of the last sample at or before it that was not a rest (−1 before any)."""
    return np.maximum.accumulate(np.where(rest, -1, np.arange(rest.size)))


def _seconds_since_load(time_s: np.ndarray, last_load: np.ndarray) -> np.ndarray:
    """For each sample, the seconds since its :func:`_last_load` (``inf`` before any load)."""
    return np.where(last_load >= 0, time_s - time_s[np.maximum(last_load, 0)], np.inf)


def capacity_end_point(time_s: np.ndarray, current_a: np.ndarray, capacity_ah: float) -> int:
    """The closing point of the two-point check: within the last :data:`CAPACITY_END_WINDOW_S`,
    the end of the latest rest of at least :data:`RELAX_REST_MIN_S`, else the latest rest sample,
    else the sample of least current.

    A cut-off under high current is a poor OCV anchor (the overpotential is most of the
    voltage, and a kinetics-limited cell reaches ``v_min`` at any SOC); the lightest load just
    before it says more about the SOC, and a long rest before it more still: its own relaxation
    bounds the OCV there (:func:`two_point_capacity`).  A pulse test that runs into its cut-off has
    a short rest after its last pulse and a long one before it.  A recording that ends in a rest
    closes at its last sample.
    """
    window = np.flatnonzero(time_s >= time_s[-1] - CAPACITY_END_WINDOW_S)
    rest = resting(time_s, current_a, capacity_ah, REST_MAX_C)
    if not rest[window].any():
        return int(window[np.argmin(np.abs(current_a[window]))])
    candidates = window[rest[window]]
    long_rest = candidates[_seconds_since_load(time_s, _last_load(rest))[candidates] >= RELAX_REST_MIN_S]
    return int(long_rest[-1]) if long_rest.size else int(candidates[-1])


def _relaxed_soc_interval(table, time_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray,
                          temp_c: float, origin: int, end: int) -> tuple[tuple[float, float, float], float]:
    """``(SOC low, mid, high)`` at the end ``end`` of the rest that began at ``origin``, with its OCV
    bounded by the rest's own relaxation and not by a model: the voltage relaxes towards the OCV
    (up after a discharge, down after a charge), and what is still to come is read as a diffusion
    tail from the rest's last quarter (``2·t·dV/dt``, :func:`_rest_end_line`), taken twice with two
    standard errors, and widened by :data:`CAPACITY_OCV_FLOOR_V`.  Also the relaxation still to come, V."""
    _, remaining, se, _ = _rest_end_line(time_s, voltage_v, origin, end + 1)
    toward = math.copysign(1.0, float(current_a[origin - 1]))
    v = float(voltage_v[end])
    far = v + toward * (2.0 * abs(remaining) + (2.0 * se if math.isfinite(se) else 0.0))
    ocv = np.array([min(v, far) - CAPACITY_OCV_FLOOR_V, v + toward * abs(remaining), max(v, far) + CAPACITY_OCV_FLOOR_V])
    soc = table.soc_from_ocv(ocv, temp_c)
    return (float(soc[0]), float(soc[1]), float(soc[2])), remaining


def two_point_capacity(time_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray, temperature_c: np.ndarray,
                       v_model: np.ndarray, soc_model: np.ndarray, table, capacity_ah: float, i_start: int,
                       i_end: int, r_ohm: float, bias: dict | None = None) -> dict:
    """Capacity from the charge between two OCV-anchored points (module docstring, ``capacity``).

    ``v_model``/``soc_model`` are the base model's voltage and SOC along the recording
    (Coulomb counting with ``capacity_ah``); ``i_start`` is the sample standing for the
    opening OCV (the end of the opening rest), ``i_end`` the closing one
    (:func:`capacity_end_point`); ``r_ohm`` the base model's ohmic resistance.  The closing
    sample is the only held-out voltage it reads (the pipeline leaves it out of every
    held-out score).  A current offset the rests measured
    (``bias`` from :func:`rest_current_offset`, when nominated) is taken out of the charge.
    """
    out = {"nominated": False, "direct": True, "statistic": 1.0, "what": "capacity / stated capacity from the "
           "charge between the opening rest and the end over their SOC difference on the OCV table",
           "threshold": CAPACITY_MIN_ERROR, "min_span_soc": CAPACITY_MIN_SPAN, "ocv_floor_v": CAPACITY_OCV_FLOOR_V}
    if i_end - i_start < 10:
        return out
    if time_s[i_start] - time_s[0] < CAPACITY_MIN_OPENING_REST_S:
        out["skipped"] = f"no opening rest of {CAPACITY_MIN_OPENING_REST_S:.0f} s to anchor the start"
        return out
    eta = v_model - table.ocv(soc_model, temperature_c)
    s0 = _soc_interval(table, float(voltage_v[i_start]), float(eta[i_start]), float(temperature_c[i_start]))
    # under load at the end (before a cut-off) the ohmic drop is the base's R_ohm (identified from the
    # voltage steps of the fit part) times the current; only the polarisation is uncertain
    # (no larger than the model's whole overpotential, and of its sign)
    ohmic, eta_end = -r_ohm * float(current_a[i_end]), float(eta[i_end])
    ohmic = math.copysign(min(abs(ohmic), abs(eta_end)), eta_end) if ohmic * eta_end > 0 else 0.0
    s1 = _soc_interval(table, float(voltage_v[i_end]), eta_end, float(temperature_c[i_end]), ohmic)
    end_bound, remaining = "model", None
    load = int(_last_load(resting(time_s, current_a, capacity_ah, REST_MAX_C))[i_end])
    if 0 <= load < i_end and time_s[i_end] - time_s[load] >= RELAX_REST_MIN_S:
        # the end of a long rest: its own relaxation bounds the OCV, not the model, whose polarisation
        # there is an extrapolation of the fit part and can be off by tens of mV
        s1, remaining = _relaxed_soc_interval(table, time_s, current_a, voltage_v, float(temperature_c[i_end]),
                                              load + 1, i_end)
        end_bound = "relaxation"
    # charge drawn in "SOC of the stated capacity", as the model counts it
    drawn = float(soc_model[i_start] - soc_model[i_end])
    hours = float(time_s[i_end] - time_s[i_start]) / SECONDS_PER_HOUR
    drawn_lo = drawn_hi = drawn
    if bias and bias.get("se_a"):
        b = float(bias["offset_a"]) if bias.get("nominated") else 0.0
        # measured = true + b: the true charge is the measured one minus b over the time
        drawn -= b * hours / capacity_ah
        spread = 3.0 * float(bias["se_a"]) * hours / capacity_ah
        drawn_lo, drawn_hi = drawn - spread, drawn + spread
    out.update(soc_start=round(s0[1], 4), soc_start_range=[round(s0[0], 4), round(s0[2], 4)],
               soc_end=round(s1[1], 4), soc_end_range=[round(s1[0], 4), round(s1[2], 4)],
               overpotential_start_mv=round(1000 * float(eta[i_start]), 1),
               overpotential_end_mv=round(1000 * float(eta[i_end]), 1), ohmic_end_mv=round(1000 * ohmic, 1),
               end_bound=end_bound,
               relaxation_to_come_mv=None if remaining is None else round(1000 * remaining, 1),
               drawn_soc=round(drawn, 4),
               t_start_s=float(time_s[i_start]), t_end_s=float(time_s[i_end]))
    if drawn < 0:  # a charge: the same check with the points' roles swapped
        drawn, drawn_lo, drawn_hi = -drawn, -drawn_hi, -drawn_lo
        s0, s1 = s1, s0
    span, span_lo, span_hi = s0[1] - s1[1], s0[0] - s1[2], s0[2] - s1[0]
    if drawn < 1e-6 or span <= 0:
        return out
    ratio = drawn / span
    lo = drawn_lo / span_hi
    hi = drawn_hi / span_lo if span_lo > 0 else float("inf")
    out.update(statistic=round(ratio, 4), capacity_scale=ratio, capacity_scale_range=[round(lo, 4), round(hi, 4)],
               nominated=bool(span >= CAPACITY_MIN_SPAN and (hi <= 1.0 - CAPACITY_MIN_ERROR
                                                            or lo >= 1.0 + CAPACITY_MIN_ERROR)))
    return out


def _rest_end_line(time_s: np.ndarray, voltage_v: np.ndarray, origin: int, stop: int) -> tuple[float, float, float, slice]:
    """A line through the last quarter of the rest ``[origin, stop)``, time counted from
    ``origin``: ``(voltage at the rest end, relaxation still to come 2·t·dV/dt, its standard
    error, the tail's samples)``.  ``2·t·dV/dt`` is what is left of a diffusion tail
    ``V∞ − A·t^−1/2`` at the rest end."""
    tail = slice(origin + 3 * (stop - origin) // 4, stop)
    t_end = float(time_s[stop - 1] - time_s[origin])
    t, v = time_s[tail] - time_s[origin], voltage_v[tail]
    if t.size > 3:
        (slope, level), cov = np.polyfit(t, v, 1, cov=True)
        se = 2.0 * t_end * math.sqrt(max(cov[0, 0], 0.0))
    else:  # too few samples for a standard error (a slowly sampled recording)
        slope, level = np.polyfit(t, v, 1)
        se = math.inf
    return float(level + slope * t_end), float(2.0 * t_end * slope), se, tail


def rest_relaxation(time_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray, capacity_ah: float,
                    usable: np.ndarray | None = None, min_rest_s: float = RELAX_REST_MIN_S) -> dict:
    """Relaxation still running at the ends of rests of at least ``min_rest_s``, over the ohmic
    step (module docstring, ``diffusion``).  ``usable`` (optional mask): only rests that lie wholly
    inside it, with the load sample before them, are read (the pipeline passes the fit part)."""
    out = {"nominated": False, "statistic": 0.0, "threshold": RELAX_MIN_RATIO, "min_z": RELAX_MIN_Z,
           "min_rest_s": min_rest_s, "min_step_c": RELAX_MIN_STEP_C,
           "what": f"relaxation still to come at the ends of rests >= {min_rest_s:.0f} s (diffusion tail "
                   "2·t·dV/dt) over the ohmic step when the current stopped (median, no model)"}
    rests = []
    last_load = _last_load(resting(time_s, current_a, capacity_ah, REST_MAX_C))
    for a, b in rest_runs(time_s, current_a, capacity_ah):
        j = int(last_load[a - 1]) if a > 0 else -1  # the load sample before the rest, −1 if none
        start = j + 1
        if j < 0 or time_s[b - 1] - time_s[start] < min_rest_s:
            continue  # the opening rest, or too short
        if abs(current_a[j]) < RELAX_MIN_STEP_C * capacity_ah or (usable is not None and not usable[j:b].all()):
            continue
        sign = math.copysign(1.0, current_a[j])  # after a discharge the voltage rises
        step = sign * float(voltage_v[start] - voltage_v[j])
        if step <= 0:
            continue
        _, remaining, se, _ = _rest_end_line(time_s, voltage_v, start, b)
        rests.append((float(time_s[b - 1]), step, sign * remaining, se, float(current_a[j])))
    out["n_rests"] = len(rests)
    if not rests:
        out["skipped"] = (f"no rest of {min_rest_s:.0f} s after a load step of {RELAX_MIN_STEP_C:g}C"
                          + (" in the fit part" if usable is not None else ""))
        return out
    ends, step, remaining, se, step_a = (np.array(c) for c in zip(*rests))
    ratio = remaining / step
    z = float(remaining.sum() / math.sqrt(max(float((se**2).sum()), 1e-30)))
    stat = float(np.median(ratio))
    out.update(statistic=round(stat, 3), z=round(z, 2), rest_end_s=ends.tolist(),
               step_mv=[round(1000 * float(x), 1) for x in step], remaining_mv=[round(1000 * float(x), 1) for x in remaining],
               ratio=[round(float(x), 3) for x in ratio], step_current_a=step_a.tolist(),
               nominated=bool(stat >= RELAX_MIN_RATIO and z >= RELAX_MIN_Z),
               direct=bool(stat >= RELAX_DIRECT_RATIO and z >= RELAX_MIN_Z))
    return out


def rest_branch_offset(time_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray, temperature_c: np.ndarray,
                       table, capacity_ah: float) -> dict:
    """The hysteresis half-gap measured at the ends of long rests (module docstring, ``hysteresis``).

    ``rest_tails`` in the result are the ``[start, stop)`` samples it read (the last quarter of
    each rest): the pipeline leaves them out of every held-out score, as it does the capacity
    check's end point, so no held-out score contains a voltage a signature measured."""
    out = {"nominated": False, "direct": True, "statistic": 0.0, "what": "z of the branch half-gap U_H that the "
           f"ends of rests >= {BRANCH_REST_MIN_S:.0f} s show against the OCV table (Eq.-1 direction state, no model)",
           "threshold": BRANCH_MIN_Z, "min_rest_s": BRANCH_REST_MIN_S, "min_rests": BRANCH_MIN_RESTS, "min_half_gap_v": BRANCH_MIN_HALF_GAP_V,
           "max_spread": BRANCH_MAX_SPREAD, "max_relaxation": BRANCH_MAX_RELAXATION}
    ends, v_end, relax, tails = [], [], [], []
    for a, b in rest_runs(time_s, current_a, capacity_ah):
        if a < REST_MIN_SAMPLES or time_s[b - 1] - time_s[a] < BRANCH_REST_MIN_S:
            continue  # the opening rest's branch is the unknown history
        level, remaining, _, tail = _rest_end_line(time_s, voltage_v, a, b)
        ends.append(b - 1)
        tails.append([int(tail.start), int(b)])
        v_end.append(level)
        relax.append(remaining)
    out["n_rests"], out["rest_tails"] = len(ends), []
    if len(ends) < BRANCH_MIN_RESTS:
        out["skipped"] = f"{len(ends)} rests of {BRANCH_REST_MIN_S:.0f} s after load (needs {BRANCH_MIN_RESTS})"
        return out
    out["rest_tails"] = tails
    idx, v = np.array(ends), np.array(v_end)
    drawn = np.concatenate([[0.0], np.cumsum(0.5 * (current_a[1:] + current_a[:-1]) * np.diff(time_s))])
    q = drawn[idx] / (SECONDS_PER_HOUR * capacity_ah)
    best = None
    for rate in BRANCH_RATES:
        h = direction_state(time_s, current_a, capacity_ah, rate)[idx]

        def resid(x, h=h):
            # U_H > 0 puts the discharge branch (h = -1) below the table
            return table.ocv(x[0] - q, temperature_c[idx]) + x[1] * h - v

        fit = least_squares(resid, [float(table.soc_from_ocv(np.array(v[0]), temperature_c[idx[0]])) + q[0], 0.0])
        if best is None or fit.cost < best[1].cost:
            best = (rate, fit)
    rate, fit = best
    n = idx.size
    var = 2.0 * fit.cost / max(n - 3, 1)  # s0, U_H and the chosen rate
    cov = np.linalg.pinv(fit.jac.T @ fit.jac) * var
    half_gap, se = float(fit.x[1]), float(math.sqrt(max(cov[1, 1], 1e-30)))
    spread = math.sqrt(var) / max(abs(half_gap), 1e-9)
    relaxation = float(np.median(np.abs(relax))) / max(abs(half_gap), 1e-9)
    z = half_gap / se
    out.update(statistic=round(z, 2), half_gap_v=half_gap, half_gap_se_v=se, rate=rate, soc0=round(float(fit.x[0]), 4),
               spread=round(spread, 3), relaxation=round(relaxation, 3), rest_end_s=[float(time_s[k]) for k in idx],
               nominated=branch_nominates(z, half_gap, spread, relaxation))
    return out


def branch_nominates(z: float, half_gap_v: float, spread: float, relaxation: float,
                     min_z: float = BRANCH_MIN_Z, min_half_gap_v: float = BRANCH_MIN_HALF_GAP_V) -> bool:
    """Whether the rest ends' half-gap fit (:func:`rest_branch_offset`, read from at least
    :data:`BRANCH_MIN_RESTS` rests) measures a hysteresis, at the levels given (``research.devset``
    replays other levels through this)."""
    return bool(z >= min_z and half_gap_v >= min_half_gap_v and spread <= BRANCH_MAX_SPREAD
                and relaxation <= BRANCH_MAX_RELAXATION)


def direction_nominates(z: float, half_gap_v: float, min_z: float = DIRECTION_MIN_Z,
                        min_half_gap_v: float = BRANCH_MIN_HALF_GAP_V) -> bool:
    """Whether the direction state in the base residual (:func:`direction_offset`) nominates a
    hysteresis, at the levels given."""
    return bool(z >= min_z and half_gap_v >= min_half_gap_v)


def opening_temperature_c(time_s: np.ndarray, temperature_c: np.ndarray) -> float:
    """Median temperature over the first :data:`OPENING_WINDOW_S` of the recording."""
    first = time_s <= time_s[0] + OPENING_WINDOW_S
    return float(np.median(temperature_c[first]))


def coldest_temperature_c(temperature_c: np.ndarray) -> float:
    """The recording's coldest temperature: its 1st percentile (one noisy sample does not set it)."""
    return float(np.percentile(temperature_c, 1.0))


def temperature_signature(time_s: np.ndarray, current_a: np.ndarray, temperature_c: np.ndarray, capacity_ah: float,
                          nominal_ambient_c: float | None = NOMINAL_AMBIENT_C) -> dict:
    """The ``temperature`` signature: the constant-ambient misfit, or an opening away from the
    nominal ambient followed by a moving temperature (module docstring).  ``nominal_ambient_c``
    None: the misfit alone."""
    amb = ambient_drift_k(time_s, current_a, temperature_c, capacity_ah)
    t_open = opening_temperature_c(time_s, temperature_c)
    t_cold = coldest_temperature_c(temperature_c)
    drift = amb["rms_k"] >= AMBIENT_DRIFT_K
    moves = nominal_ambient_c is not None and amb["range_k"] >= TEMP_RANGE_K
    opens_off = moves and abs(t_open - nominal_ambient_c) >= OPENING_TEMP_K
    cools_below = moves and nominal_ambient_c - t_cold >= OPENING_TEMP_K
    why = ("the temperature does not follow a constant ambient" if drift else
           f"it opens {t_open - nominal_ambient_c:+.1f} K from the nominal {nominal_ambient_c:g} °C ambient and then "
           f"moves {amb['range_k']:.1f} K" if opens_off else
           f"it cools to {t_cold:.1f} °C, {nominal_ambient_c - t_cold:.1f} K below the nominal {nominal_ambient_c:g} °C "
           f"ambient, which self-heating cannot do" if cools_below else "")
    # an ambient measured away from the nominal one is a direct measurement of the departure (the
    # cell ran at another temperature than the base model's); a self-heating misfit alone is not:
    # slow kinetics or a larger resistance heat the cell differently too
    return {"nominated": bool(drift or opens_off or cools_below), "direct": bool(opens_off or cools_below),
            "statistic": round(amb["rms_k"], 3),
            "what": "RMS misfit (K) of a constant-ambient self-heating model to the temperature; opening and coldest "
                    "temperature against the nominal ambient",
            "threshold": AMBIENT_DRIFT_K, **{k: round(v, 3) for k, v in amb.items()},
            "opening_temp_c": round(t_open, 2), "coldest_temp_c": round(t_cold, 2), "nominal_ambient_c": nominal_ambient_c,
            "opening_threshold_k": OPENING_TEMP_K, "range_threshold_k": TEMP_RANGE_K, "why": why}


def signatures(time_s: np.ndarray, current_a: np.ndarray, temperature_c: np.ndarray, capacity_ah: float,
               nominal_ambient_c: float | None = NOMINAL_AMBIENT_C) -> dict:
    """``{effect: {"nominated": bool, "statistic": float, ...}}`` for the effects that have one."""
    return {
        "current_bias": rest_current_offset(time_s, current_a, capacity_ah),
        "temperature": temperature_signature(time_s, current_a, temperature_c, capacity_ah, nominal_ambient_c),
    }


def step_kinetics(time_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray, temperature_c: np.ndarray,
                  capacity_ah: float, usable: np.ndarray | None = None) -> dict:
    """The apparent exchange current from the voltage across current steps (module docstring,
    ``kinetics``).  ``usable`` (optional mask): only steps whose four samples lie inside it."""
    out = {"nominated": False, "statistic": None, "threshold": KINETICS_MAX_I0_C, "min_steps": STEP_MIN_STEPS,
           "min_step_c": STEP_MIN_C, "min_peak_c": STEP_MIN_PEAK_C,
           "what": "apparent exchange current i0 (C) from the curvature of the voltage change across current "
                   "steps against the current (Butler-Volmer; the 95 % upper bound must be below the threshold; "
                   "no model)"}
    if current_a.size < 4:
        out.update(n_steps=0, skipped="fewer than 4 samples")
        return out
    j = current_steps(time_s, current_a, capacity_ah, usable)
    c1, c2 = current_a[j] / capacity_ah, current_a[j + 1] / capacity_ah
    out["n_steps"] = int(j.size)
    peak = steps_peak_c(current_a, j, capacity_ah)
    out["peak_c"] = round(peak, 3)
    if not steps_resolve_kinetics(j.size, peak):
        out["skipped"] = (f"{j.size} current steps of at least {STEP_MIN_C:g}C reaching {peak:.2f}C "
                          f"(needs {STEP_MIN_STEPS} reaching {STEP_MIN_PEAK_C:g}C)")
        return out
    dv = voltage_v[j + 1] - voltage_v[j]
    d_amp = current_a[j + 1] - current_a[j]
    vt = kinetic_voltage_v(0.5 * (temperature_c[j] + temperature_c[j + 1]))

    def resid(th):
        x = math.exp(th[1])
        return dv + th[0] * d_amp + vt * (np.arcsinh(c2 / (2 * x)) - np.arcsinh(c1 / (2 * x)))

    lo, hi = math.log(0.005), math.log(100.0)
    r0 = float(max(-(dv @ d_amp) / max(float(d_amp @ d_amp), 1e-30), 0.0))
    best = None
    for x0 in (0.03, 0.1, 0.3, 1.0, 3.0, 10.0):
        fit = least_squares(resid, [r0, math.log(x0)], bounds=([0.0, lo], [10.0, hi]))
        if best is None or fit.cost < best.cost:
            best = fit
    dof = max(j.size - 2, 1)
    var = 2.0 * best.cost / dof
    cov = np.linalg.pinv(best.jac.T @ best.jac) * var
    ln_x, se = float(best.x[1]), float(math.sqrt(max(cov[1, 1], 0.0)))
    upper = math.exp(min(ln_x + 1.96 * se, hi))
    i0_c = math.exp(ln_x)
    # resolved: the 95 % interval clears the search's lower bound (an i0 pinned there is no measurement)
    resolved = bool(ln_x - 1.96 * se > lo)
    out.update(statistic=round(i0_c, 4), i0_c=i0_c, i0_upper_c=upper, ln_i0_se=se, r_step_ohm=float(best.x[0]),
               rms_mv=round(1000 * math.sqrt(var), 3), resolved=resolved,
               nominated=bool(upper < KINETICS_MAX_I0_C and resolved))
    return out


def direction_offset(time_s: np.ndarray, current_a: np.ndarray, residual_v: np.ndarray, capacity_ah: float,
                     usable: np.ndarray) -> dict:
    """Hysteresis on a drive cycle: the part of the base residual the Eq.-1 direction state
    explains beyond any linear filter of the current (module docstring, ``hysteresis``).
    ``usable``: the samples that enter the regression (the pipeline passes the fit part)."""
    out = {"nominated": False, "statistic": 0.0, "threshold": DIRECTION_MIN_Z, "min_half_gap_v": BRANCH_MIN_HALF_GAP_V,
           "what": "z of the half-gap the Eq.-1 direction state explains in the high-passed base residual beyond "
                   "the C-rate and its low-passes (drive cycles; model-based)"}
    dt = float(np.median(np.diff(time_s))) if time_s.size > 1 else 1.0
    width = max(round(DIRECTION_HIGHPASS_S / max(dt, 1e-9)), 3)
    mask = usable.copy()
    mask[: width // 2] = False
    mask[-(width // 2):] = False
    n_min = 3 * width
    if int(mask.sum()) < n_min:
        out["skipped"] = f"{int(mask.sum())} usable samples (needs {n_min})"
        return out
    def highpass(x: np.ndarray) -> np.ndarray:
        return (x - uniform_filter1d(x, width, mode="nearest"))[mask]

    crate = current_a / capacity_ah
    linear = [highpass(c) for c in [crate] + [lowpass(crate, time_s, tau) for tau in DIRECTION_LOWPASS_S]]
    y = highpass(residual_v)
    best = None
    for rate in BRANCH_RATES:
        a = np.column_stack([*linear, highpass(direction_state(time_s, current_a, capacity_ah, rate))])
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        e = y - a @ coef
        sse = float(e @ e)
        if best is None or sse < best[0]:
            best = (sse, rate, coef, e, a)
    sse, rate, coef, e, a = best
    tau = integrated_autocorr_time(e)
    cov = np.linalg.pinv(a.T @ a) * sse / max(e.size - a.shape[1], 1) * tau
    half_gap, se = float(coef[-1]), float(math.sqrt(max(cov[-1, -1], 1e-30)))
    z = half_gap / se
    out.update(statistic=round(z, 2), half_gap_v=half_gap, half_gap_se_v=se, rate=rate, tau_int=round(tau, 1),
               n_samples=int(e.size),
               nominated=direction_nominates(z, half_gap))
    return out
