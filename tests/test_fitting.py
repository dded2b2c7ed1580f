"""Base-parameter fitting recovers what the model was simulated with."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from service.cell.fitting import (
    BOUNDS,
    BOUNDS_MIN_CAPACITY_AH,
    KINETICS_BOUNDS,
    FitSegment,
    decode,
    excited_window,
    fit_parameters,
    kinetics_bounds,
    point_from_x,
    search_bounds,
)
from service.cell.profile import (
    FARADAY,
    GAS_CONSTANT,
    KELVIN,
    CellProfile,
    Extensions,
    HysteresisSpec,
    OcvSpec,
    ParameterPoint,
    SocResistanceSpec,
)
from service.cell.trajectory import simulate
from service.recording import Recording

TRUE = ParameterPoint(r_ohm=0.030, r_ct=0.015, c_dl=300.0, m=0.9, r_df=0.020, c_df=9000.0, n=0.85)


def nmc_like_ocv() -> OcvSpec:
    soc = np.linspace(0, 1, 41)
    ocv = 3.3 + 0.75 * soc + 0.12 * np.tanh((soc - 0.08) / 0.05) - 0.06 * np.exp(-((soc - 0.55) / 0.1) ** 2)
    return OcvSpec(soc=soc.tolist(), ocv_v=[ocv.tolist()])


def profile(point: ParameterPoint = TRUE, **kw) -> CellProfile:
    return CellProfile(capacity_ah=2.0, ocv=nmc_like_ocv(), parameters=[point], **kw)


def pulse_current(n: int, capacity_ah: float, seed: int, dt_s: float = 1.0) -> np.ndarray:
    """Steps of 10-120 s between -0.5C and 2C with rests; net discharge."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        level = rng.choice([2.0, 1.5, 1.0, 0.5, 0.0, 0.0, -0.5]) * capacity_ah
        out += [level] * int(rng.integers(10, 120) / dt_s)
    cur = np.array(out[:n], dtype=float)
    cur[: int(60 / dt_s)] = 0.0
    return cur


def _pulse_drive(prof, n: int, seed: int, scale: float = 1.0, temp_c: float = 25.0):
    """``(t, i, temp, v)``: a 1-s pulse drive of ``n`` samples simulated with ``prof`` from SOC 0.95."""
    t = np.arange(n, dtype=float)
    i = pulse_current(n, 2.0, seed) * scale
    temp = np.full(n, temp_c)
    v, _ = simulate(prof, t, i, temp, 0.95)
    return t, i, temp, v


def test_fit_recovers_known_parameters():
    n = 2400
    t, i, temp, v = _pulse_drive(profile(), n, 1)
    v = v + np.random.default_rng(2).normal(0, 0.001, n)
    start = profile(ParameterPoint(r_ohm=0.01, r_ct=0.01, c_dl=100, m=0.8, r_df=0.01, c_df=1000, n=0.8))
    res = fit_parameters(start, [FitSegment(t, i, v, temp, soc0=0.95)], max_seconds=120, seed=0, de_maxiter=30)
    assert res.rmse_mv < 1.3  # the noise is 1 mV
    p = res.point
    assert p.r_ohm == pytest.approx(TRUE.r_ohm, rel=0.1)
    # the instantaneous + charge-transfer resistance (what a 10 s pulse sees) is identified well
    assert p.r_ohm + p.r_ct == pytest.approx(TRUE.r_ohm + TRUE.r_ct, rel=0.1)
    tau = (p.r_ct * p.c_dl) ** (1 / p.m)
    tau_true = (TRUE.r_ct * TRUE.c_dl) ** (1 / TRUE.m)
    assert 0.5 < tau / tau_true < 2.0
    assert 0.3 <= p.m <= 1.0 and 0.3 <= p.n <= 1.0
    assert res.n_evaluations > 0


def test_fit_hysteresis_recovers_u_h():
    n = 1200
    t = np.arange(n, dtype=float)
    i = pulse_current(n, 2.0, 5)
    temp = np.full(n, 25.0)
    prof = profile(hysteresis=HysteresisSpec(u_h_max_v=0.025, rate=30.0))
    v, _ = simulate(prof, t, i, temp, 0.95, u_h0=0.025)
    v = v + np.random.default_rng(3).normal(0, 0.001, n)
    res = fit_parameters(profile(), [FitSegment(t, i, v, temp, soc0=0.95, u_h0=0.025)], fit_hysteresis=True,
                         max_seconds=120, x0=TRUE, de_maxiter=15)
    assert res.hysteresis is not None
    assert res.hysteresis.u_h_max_v == pytest.approx(0.025, abs=0.006)
    assert res.rmse_mv < 1.5


def test_segment_validation_and_window():
    with pytest.raises(ValueError, match="voltage_v"):
        FitSegment(np.arange(5.0), np.zeros(5), np.zeros(4), np.zeros(5), soc0=0.5)
    with pytest.raises(ValueError, match="increase"):
        FitSegment(np.array([0.0, 1, 1, 2]), np.zeros(4), np.zeros(4), np.zeros(4), soc0=0.5)
    n = 3000
    i = pulse_current(n, 2.0, 7)
    seg = FitSegment(np.arange(n, dtype=float), i, np.full(n, 3.7), np.full(n, 25.0), soc0=0.9)
    w = excited_window(seg, 1000, 2.0)
    assert len(w) == 1000
    a = int(w.time_s[0])
    assert w.soc0 == pytest.approx(0.9 - float(np.sum(i[1:a + 1])) / 7200.0)
    assert math.isfinite(w.soc0)


def test_fit_kinetics_recovers_exchange_current():
    """Pulses at several currents separate the Butler-Volmer i0 from the linear R_ct."""
    n = 2400
    truth = TRUE.model_copy(update={"temp_c": 0.0, "i0_a": 1.0})
    # up to 4C, where a 1 A exchange current bends the curve
    t, i, temp, v = _pulse_drive(profile(truth), n, 7, scale=2.0, temp_c=0.0)
    v = v + np.random.default_rng(4).normal(0, 0.001, n)
    start = profile(ParameterPoint(temp_c=0.0, r_ohm=0.01, r_ct=0.01, c_dl=100, m=0.8, r_df=0.01, c_df=1000, n=0.8))
    linear = fit_parameters(start, [FitSegment(t, i, v, temp, soc0=0.95)], max_seconds=60, x0=truth, de_maxiter=10)
    res = fit_parameters(start, [FitSegment(t, i, v, temp, soc0=0.95)], fit_kinetics=True, max_seconds=120,
                         x0=truth.model_copy(update={"i0_a": 5.0}), de_maxiter=20)
    assert res.point.i0_a == pytest.approx(1.0, rel=0.25)
    assert res.rmse_mv < 1.3  # the noise is 1 mV
    assert linear.point.i0_a is None and linear.rmse_mv > 2 * res.rmse_mv


def test_pure_ohmic_floor_holds_r_ohm_above_the_kinetic_drop():
    """``min_pure_ohm``: the search cannot give the kinetic term the whole instantaneous drop;
    every candidate it simulates, and the point it returns, keep R_ohm at least that much above
    the Butler-Volmer term's linear drop (``socd fit --pure-ohmic-share``)."""
    truth = TRUE.model_copy(update={"temp_c": 0.0, "i0_a": 1.0})
    t, i, temp, v = _pulse_drive(profile(truth), 1200, 7, scale=2.0, temp_c=0.0)
    floor_pure = 0.02
    # a candidate with almost no R_ohm is simulated at the floor
    x = np.array([[math.log(1e-4), math.log(0.015), math.log(5.0), 0.9, math.log(0.02), math.log(30.0), 0.85,
                   math.log(1.0)]])
    lin = 2.0 * GAS_CONSTANT * KELVIN / FARADAY / 2.0
    params = decode(x, profile(truth), 0.0, False, fit_kinetics=True, min_pure_ohm=floor_pure)
    assert params.r_ohm[0] == pytest.approx(lin + floor_pure)
    assert decode(x, profile(truth), 0.0, False, fit_kinetics=True).r_ohm[0] == pytest.approx(lin)
    res = fit_parameters(profile(truth), [FitSegment(t, i, v, temp, soc0=0.95)], fit_kinetics=True, max_seconds=30,
                         x0=truth, de_maxiter=3, min_pure_ohm=floor_pure)
    kinetic = 2.0 * GAS_CONSTANT * (res.point.temp_c + KELVIN) / FARADAY / (2.0 * res.point.i0_a)
    assert res.point.r_ohm >= (kinetic + floor_pure) * (1 - 1e-9)
    # without a Butler-Volmer term the floor is the pure part alone
    plain = decode(x[:, :7], profile(TRUE), 25.0, False, min_pure_ohm=floor_pure)
    assert plain.r_ohm[0] == pytest.approx(floor_pure)


def test_i0_interpolates_like_a_resistance_and_is_all_or_none():
    # R_ohm 60 mΩ holds the linear kinetic drop of i0 0.5 A at 0 °C (47 mΩ; see the next test)
    pts = [TRUE.model_copy(update={"temp_c": 0.0, "i0_a": 0.5, "r_ohm": 0.06}),
           TRUE.model_copy(update={"temp_c": 25.0, "i0_a": 2.0})]
    prof = profile(pts[0]).model_copy(update={"parameters": pts})
    i0 = prof.parameters_at(np.array([0.0, 12.0, 25.0])).kinetics_i0_a
    assert i0[0] == pytest.approx(0.5) and i0[2] == pytest.approx(2.0)
    assert 0.5 < i0[1] < 2.0
    # the diagnose extension, when set, is added on top and takes precedence
    ext = prof.model_copy(update={"extensions": Extensions(kinetics_i0_a=3.0)})
    assert ext.parameters_at(12.0).kinetics_i0_a[0] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="i0_a must be given at every temperature"):
        CellProfile(capacity_ah=2.0, ocv=nmc_like_ocv(),
                    parameters=[pts[0], TRUE.model_copy(update={"temp_c": 25.0})])


def test_r_ohm_below_the_linear_kinetic_drop_is_rejected_and_never_fitted():
    """The model's drop is R_ohm·I + 2RT/F (asinh(I/2i0) − I/2i0): with R_ohm below 2RT/F/(2 i0)
    a large discharge lifts the voltage above the OCV.  A profile like that is refused with the
    temperature point named, and neither the fit's search coordinates nor diagnose's kinetics
    extension can produce one."""
    lin_0c = 2.0 * GAS_CONSTANT * KELVIN / FARADAY / (2.0 * 0.5)  # i0 0.5 A at 0 °C: 47 mΩ
    bad = TRUE.model_copy(update={"temp_c": 0.0, "i0_a": 0.5, "r_ohm": 0.6 * lin_0c})
    with pytest.raises(ValueError, match=r"parameters\[0\] \(0 °C\).*below the linear Butler-Volmer drop"):
        profile(bad)
    # the same point is fine at the floor, and an extension's i0 is checked against every point
    profile(bad.model_copy(update={"r_ohm": lin_0c}))
    with pytest.raises(ValueError, match="below the linear Butler-Volmer drop"):
        profile(extensions=Extensions(kinetics_i0_a=0.2))  # TRUE's 30 mΩ < 128 mΩ at 25 °C
    # a SOC scale of R_ohm below 1 raises the floor by its inverse
    table = SocResistanceSpec(soc=[0.0, 1.0], temps_c=[0.0], r_ohm_scale=[[0.5, 1.0]], r_pol_scale=[[1.0, 1.0]])
    with pytest.raises(ValueError, match="below the linear Butler-Volmer drop"):
        profile(bad.model_copy(update={"r_ohm": 1.5 * lin_0c}), extensions=Extensions(soc_resistance=table))
    assert profile(TRUE, extensions=Extensions(soc_resistance=table)).min_r_ohm_scale(0.0) == pytest.approx(0.5)
    # over several temperatures: the lowest of any of them
    two = SocResistanceSpec(soc=[0.0, 1.0], temps_c=[0.0, 25.0], r_ohm_scale=[[0.8, 1.0], [0.6, 1.0]],
                            r_pol_scale=[[1.0, 1.0], [1.0, 1.0]])
    scaled = profile(TRUE, extensions=Extensions(soc_resistance=two))
    assert scaled.min_r_ohm_scale(0.0) == pytest.approx(0.8)
    assert scaled.min_r_ohm_scale(np.array([0.0, 25.0])) == pytest.approx(0.6)

    # the fit's coordinates: R_ohm far below the floor decodes to the floor
    start = profile(ParameterPoint(temp_c=0.0, r_ohm=0.01, r_ct=0.01, c_dl=100, m=0.8, r_df=0.01, c_df=1000, n=0.8))
    x = np.array([[math.log(0.005), math.log(0.01), math.log(5.0), 0.8, math.log(0.01), math.log(40.0), 0.8,
                   math.log(0.5)]])
    dec = decode(x, start, 0.0, fit_hysteresis=False, fit_kinetics=True)
    assert dec.r_ohm[0] == pytest.approx(lin_0c)
    # so a 10 A discharge step from rest cannot lift the voltage above the OCV
    prof = profile(point_from_x(x[0], 0.0, 0.5).model_copy(update={"r_ohm": float(dec.r_ohm[0])}))
    t = np.arange(30.0)
    i = np.where(t >= 10, 10.0, 0.0)
    v, soc = simulate(prof, t, i, np.zeros_like(t), 0.8)
    assert np.all(v[10:] <= prof.ocv_table().ocv(soc[10:], 0.0) + 1e-12)

    # diagnose's kinetics extension lifts R_ohm the same way, in the model and in the saved profile
    from service.diagnosis.effects import EFFECTS

    kin = EFFECTS["kinetics"]
    saved = kin.to_profile({"kinetics_i0_a": 0.2}, profile(TRUE), None)
    assert saved.extensions.kinetics_i0_a == 0.2
    assert saved.parameters[0].r_ohm == pytest.approx(2.0 * GAS_CONSTANT * (25.0 + KELVIN) / FARADAY / 0.4)


def test_between_temperatures_the_pulse_resistances_are_interpolated_not_r_ohm_and_i0():
    """Between fitted temperatures the small-current resistance R_ohm and the apparent resistance at
    1C are interpolated like the other resistances, and i0 is the one that gives both; beyond the
    fitted range both are held."""
    from service.cell.profile import apparent_resistance_ohm, arrhenius_interp, kinetic_linear_ohm

    rest = {0.0: 0.05, 25.0: 0.02}
    i0 = {0.0: 0.2, 25.0: 5.0}
    pts = [TRUE.model_copy(update={"temp_c": t, "i0_a": i0[t], "r_ohm": rest[t] + float(kinetic_linear_ohm(i0[t], t))})
           for t in (0.0, 25.0)]
    prof = profile(pts[0]).model_copy(update={"parameters": pts})
    temps = np.array([0.0, 12.0, 25.0])
    par = prof.parameters_at(temps)
    assert par.r_ohm[[0, 2]] == pytest.approx([pts[0].r_ohm, pts[1].r_ohm])
    assert par.kinetics_i0_a[[0, 2]] == pytest.approx([0.2, 5.0], rel=1e-9)
    grid = np.array([0.0, 25.0])
    one_c = prof.effective_capacity_ah
    at_1c = apparent_resistance_ohm(np.array([p.r_ohm for p in pts]), np.array([0.2, 5.0]), one_c, grid)
    assert par.r_ohm[1] == pytest.approx(np.exp(arrhenius_interp(np.array([12.0]), grid, np.log([p.r_ohm for p in pts])))[0])
    want_1c = np.exp(arrhenius_interp(np.array([12.0]), grid, np.log(at_1c)))[0]
    assert apparent_resistance_ohm(par.r_ohm[1:2], par.kinetics_i0_a[1:2], one_c, temps[1:2])[0] == pytest.approx(want_1c)
    # beyond the fitted range both are held at the end point
    warm = prof.parameters_at(np.array([35.0]))
    assert warm.r_ohm[0] == pytest.approx(pts[1].r_ohm) and warm.kinetics_i0_a[0] == pytest.approx(5.0, rel=1e-9)


def test_a_linear_point_beside_an_all_kinetic_one_interpolates_to_resistances_between_them():
    """A fit may put a temperature's whole instantaneous drop in the Butler-Volmer term (R_ohm down
    to the linear drop 2RT/F/(2 i0), i0 small) and give its neighbour linear kinetics.  Halfway
    between, the drop at every current lies between the two neighbours' drops, not below both."""
    from service.cell.profile import apparent_resistance_ohm, kinetic_linear_ohm

    all_kinetic = TRUE.model_copy(update={"temp_c": 0.0, "i0_a": 0.054,
                                          "r_ohm": float(kinetic_linear_ohm(0.054, 0.0)) + 0.002})
    linear = TRUE.model_copy(update={"temp_c": -10.0, "i0_a": 500.0, "r_ohm": 0.071})
    prof = profile(linear).model_copy(update={"parameters": [linear, all_kinetic]})
    par = prof.parameters_at(np.array([-10.0, -5.0, 0.0]))
    for current in (0.1, 0.5, 1.0, 2.0, 4.0, 6.0):
        r = apparent_resistance_ohm(par.r_ohm, par.kinetics_i0_a, current, np.array([-10.0, -5.0, 0.0]))
        assert min(r[0], r[2]) * 0.999 <= r[1] <= max(r[0], r[2]) * 1.001, (current, r)

    # beside a linear point of small resistance the two interpolations alone would put R_ohm below
    # the linear Butler-Volmer drop (the voltage would rise under a large discharge): i0 gives way
    small_linear = linear.model_copy(update={"r_ohm": 0.01})
    temps = np.linspace(-15.0, 5.0, 41)
    for pair in ([small_linear, all_kinetic], [all_kinetic.model_copy(update={"temp_c": -10.0}),
                                               small_linear.model_copy(update={"temp_c": 0.0})]):
        par = profile(pair[0]).model_copy(update={"parameters": pair}).parameters_at(temps)
        assert np.all(par.r_ohm >= kinetic_linear_ohm(par.kinetics_i0_a, temps) * (1 - 1e-9))


def test_resistances_bounded_by_the_neighbouring_temperatures():
    t, i, temp, v = _pulse_drive(profile(), 1200, 1)
    seg = [FitSegment(t, i, v, temp, soc0=0.95)]
    # a warmer point with larger resistances than this data: the fit may not go below them
    warm = TRUE.model_copy(update={"temp_c": 40.0, "r_ohm": 0.04, "r_ct": 0.02, "r_df": 0.03})
    res = fit_parameters(profile(), seg, max_seconds=30, x0=TRUE, de_maxiter=5, warmer=warm)
    p = res.point
    assert p.r_ohm >= 0.04 * (1 - 1e-9) and p.r_ct >= 0.02 * (1 - 1e-9) and p.r_df >= 0.03 * (1 - 1e-9)
    cold = TRUE.model_copy(update={"temp_c": 0.0, "r_ohm": 0.02, "r_ct": 0.01, "r_df": 0.01})
    p = fit_parameters(profile(), seg, max_seconds=30, x0=TRUE, de_maxiter=5, colder=cold).point
    assert p.r_ohm <= 0.02 * (1 + 1e-9) and p.r_ct <= 0.01 * (1 + 1e-9) and p.r_df <= 0.01 * (1 + 1e-9)
    # unconstrained, the same data gives the true ohmic resistance
    free = fit_parameters(profile(), seg, max_seconds=30, x0=TRUE, de_maxiter=5).point
    assert free.r_ohm == pytest.approx(TRUE.r_ohm, rel=0.1)


def test_pinned_coordinates_hold_and_are_not_reported_at_a_bound():
    """``socd fit --shape``: the orders (and the time-constant ratio) given are kept exactly, the
    rest is searched, and a pinned coordinate is not listed as ending on a bound."""
    t, i, temp, v = _pulse_drive(profile(), 1200, 1)
    seg = [FitSegment(t, i, v, temp, soc0=0.95)]
    pins = {"m": 0.7, "n": 0.6, "ln_tau_ratio": math.log(50.0)}
    res = fit_parameters(profile(), seg, max_seconds=30, x0=TRUE, de_maxiter=5, pinned=pins)
    p = res.point
    assert p.m == pytest.approx(0.7, abs=1e-5) and p.n == pytest.approx(0.6, abs=1e-5)
    tau_ct = (p.r_ct * p.c_dl) ** (1 / p.m)
    tau_df = (p.r_df * p.c_df) ** (1 / p.n)
    assert tau_df / tau_ct == pytest.approx(50.0, rel=1e-4)
    assert not [b for b in res.at_bounds if b.startswith(("m ", "n ", "tau_ratio"))]
    # an order pinned at its upper bound (a point on the 2-RC submodel) stays inside the range
    top = fit_parameters(profile(), seg, max_seconds=30, x0=TRUE, de_maxiter=2, pinned={"m": 1.0, "n": 1.0}).point
    assert top.m == pytest.approx(1.0, abs=1e-5) and top.n <= 1.0
    # the free search moves the orders off the pinned values, so the pin is what held them
    free = fit_parameters(profile(), seg, max_seconds=30, x0=TRUE, de_maxiter=5).point
    assert abs(free.m - 0.7) > 0.05


def test_min_slow_order_bounds_the_diffusion_branch_alone():
    """``socd fit --min-slow-order``: the diffusion branch's order n stays at or above it, started
    below it, while the double-layer order m is not held by it; a bound of 1 is refused."""
    t, i, temp, v = _pulse_drive(profile(), 1200, 1)
    seg = [FitSegment(t, i, v, temp, soc0=0.95)]
    # a point whose slow branch is far more dispersed than the bound allows
    low = TRUE.model_copy(update={"m": 0.35, "n": 0.35})
    res = fit_parameters(profile(), seg, max_seconds=30, x0=low, de_maxiter=3, min_slow_order=0.8)
    assert res.point.n >= 0.8 - 1e-9
    assert res.point.m < 0.8 or not [b for b in res.at_bounds if b.startswith("m ")]
    with pytest.raises(ValueError, match="min_slow_order"):
        fit_parameters(profile(), seg, max_seconds=5, x0=TRUE, de_maxiter=1, min_slow_order=1.0)


def _pulse_segment(n_pulses: int, amp_a: float) -> Recording:
    """1 Hz: rest 30 s, pulse 10 s at ``amp_a``, repeated, then a rest; two clean steps per pulse."""
    block = np.concatenate([np.zeros(30), np.full(10, amp_a)])
    current = np.concatenate([np.tile(block, n_pulses), np.zeros(30)])
    t = np.arange(current.size, dtype=float)
    return Recording(path=Path("pulses.csv"), time_s=t, current_a=current, voltage_v=3.7 - 0.05 * current,
                     temperature_c=np.full(t.size, 25.0))


def test_kinetics_is_fitted_only_where_current_steps_resolve_it() -> None:
    """The default ``socd fit`` rule: the exchange current is fitted at a temperature whose recordings
    have the diagnosis's kinetics signature's 20 steps reaching 0.5C, and not from a few small steps."""
    from service.characterisation.characterise import FitReport, kinetics_resolvable

    rep = FitReport(echo=lambda _: None)
    assert kinetics_resolvable([_pulse_segment(10, -2.0)], 2.0, 25.0, rep)  # 20 steps at 1C
    assert not kinetics_resolvable([_pulse_segment(9, -2.0)], 2.0, 25.0, rep)  # 18 steps
    assert not kinetics_resolvable([_pulse_segment(10, -0.8)], 2.0, 25.0, rep)  # 0.4C peak
    assert kinetics_resolvable([_pulse_segment(5, -2.0), _pulse_segment(5, -2.0)], 2.0, 0.0, rep)  # counted over recordings
    assert "not fitted (needs 20 reaching 0.5C" in rep.lines[1]


def test_temperatures_without_a_fitted_exchange_current_get_the_linear_one() -> None:
    from service.cell.fitting import LINEAR_I0_A
    from service.characterisation.characterise import with_linear_kinetics_where_unfitted

    base = ParameterPoint(temp_c=25.0, r_ohm=0.03, r_ct=0.01, c_dl=100.0, m=0.8, r_df=0.02, c_df=1000.0, n=0.9)
    cold = base.model_copy(update={"temp_c": -10.0, "i0_a": 0.2})
    mixed = with_linear_kinetics_where_unfitted([cold, base])
    assert mixed[0] == cold
    assert mixed[1].i0_a == pytest.approx(LINEAR_I0_A)
    assert mixed[1].model_copy(update={"i0_a": None}) == base
    assert with_linear_kinetics_where_unfitted([base, base]) == [base, base]


def test_fit_result_says_whether_the_time_bound_cut_the_search():
    """A search that ends by its own criteria reports ``time_bound`` False; one given almost no
    time reports True (its end point would then depend on the machine's load)."""
    t, i, temp, v = _pulse_drive(profile(), 600, 3)
    seg = [FitSegment(t, i, v, temp, soc0=0.95)]
    start = profile(ParameterPoint(r_ohm=0.01, r_ct=0.01, c_dl=100, m=0.8, r_df=0.01, c_df=1000, n=0.8))
    done = fit_parameters(start, seg, max_seconds=600, seed=0, de_maxiter=2)
    assert not done.time_bound and 0.0 < done.seconds < 600
    cut = fit_parameters(start, seg, max_seconds=1e-3, seed=0, de_maxiter=2)
    assert cut.time_bound


def test_temperature_law_scales_the_resistances_as_arrhenius():
    from service.cell.temperature_law import scaled_by_law, temperature_law_factor

    f = temperature_law_factor(40e3, np.array([-10.0, 0.0, 10.0]), 0.0)
    assert f[1] == pytest.approx(1.0) and f[0] > 1.0 > f[2]
    assert math.log(f[0]) == pytest.approx(40e3 / GAS_CONSTANT * (1 / (KELVIN - 10) - 1 / KELVIN))
    p = profile(TRUE.model_copy(update={"i0_a": 2.0})).parameters_at(0.0, n_cells=1)
    s = scaled_by_law(p, np.array([2.0]))
    assert s.r_ohm[0] == pytest.approx(2 * p.r_ohm[0]) and s.kinetics_i0_a[0] == pytest.approx(p.kinetics_i0_a[0] / 2)
    np.testing.assert_allclose(s.r[0], 2 * p.r[0])
    np.testing.assert_allclose(s.c, p.c)  # CPE coefficients kept: the time constants grow with R


def test_fit_with_the_temperature_law_gives_the_point_at_the_groups_temperature():
    """A drive that warms the cell from -10 to +8 °C (a cold drive cycle does): simulated with
    resistances that follow Arrhenius at 40 kJ/mol, the law's fit recovers the activation energy and
    the resistances at the group's temperature; one point for the whole span cannot fit the drive."""
    ea, ref = 40e3, 0.0
    temps = np.arange(-15.0, 16.0, 5.0)

    def at(t: float) -> ParameterPoint:
        f = math.exp(ea / GAS_CONSTANT * (1 / (t + KELVIN) - 1 / (ref + KELVIN)))
        return TRUE.model_copy(update={"temp_c": t, "r_ohm": TRUE.r_ohm * f, "r_ct": TRUE.r_ct * f, "r_df": TRUE.r_df * f})

    truth = profile(at(ref)).model_copy(update={"parameters": [at(t) for t in temps]})
    n = 2400
    t = np.arange(n, dtype=float)
    i = pulse_current(n, 2.0, 11)
    temp = np.linspace(-10.0, 8.0, n)
    v, _ = simulate(truth, t, i, temp, 0.95)
    v = v + np.random.default_rng(5).normal(0, 0.001, n)
    seg = [FitSegment(t, i, v, temp, soc0=0.95)]
    start = profile(at(ref))
    law = fit_parameters(start, seg, max_seconds=120, seed=0, de_maxiter=20, x0=at(ref),
                         temperature_law=True, law_ref_temp_c=ref)
    assert law.ea_j_mol == pytest.approx(ea, rel=0.2) and law.point.temp_c == ref
    assert law.point.r_ohm == pytest.approx(TRUE.r_ohm, rel=0.1)
    assert law.point.r_ohm + law.point.r_ct == pytest.approx(TRUE.r_ohm + TRUE.r_ct, rel=0.1)
    assert law.rmse_mv < 1.5  # the noise is 1 mV
    one_point = fit_parameters(start, seg, max_seconds=120, seed=0, de_maxiter=20, x0=at(ref))
    assert one_point.ea_j_mol is None and one_point.rmse_mv > 2 * law.rmse_mv


@pytest.mark.parametrize("shape", [None, "orders", "orders-ratio"])
def test_fit_shares_the_reference_temperatures_shape(tmp_path: Path, nmc_recording, nmc_ocv_csv, shape, capsys):
    """``socd fit --shape`` (and its default, ``orders``): the points at 25 and 0 °C have the same orders
    (and time-constant ratio); their resistances still differ, fitted at each temperature. Where the
    held-shape search fits worse than the 2-RC point (a time-bounded search on a loaded machine), the
    2-RC point is kept and a notice, printed even with -q, says the temperature does not share the shape."""
    from service.cell.profile import load_profile
    from service.cli import main

    # 15-min drives searched for 10 s each: about as many generations as 30-min drives get in 20 s
    drives = [nmc_recording(name=f"drive{t:g}", duration_s=900, seed=5, soc0=0.95, temp_c=t, r_ohm=r)
              for t, r in ((25.0, 0.03), (0.0, 0.06))]
    out = tmp_path / "cell.toml"
    rc = main(["fit", "--candidates", "1", *(str(d.path) for d in drives), "--ocv", str(nmc_ocv_csv), "--capacity-ah", "2.0",
               "--max-seconds", "10", "--force", *(("--shape", shape) if shape else ()), "-q", "-o", str(out),
               # the diffusion time constant's cap (1000 s) would bend a held ratio where tau_ct x ratio is above it
               *(("--max-tau-df", "1e5") if shape == "orders-ratio" else ())])
    err = capsys.readouterr().err
    assert rc == 0, err
    cold, warm = sorted(load_profile(out).parameters, key=lambda p: p.temp_c)
    if "does not share that shape" in err:
        assert (cold.m, cold.n) == (1.0, 1.0) and "0 °C: the 25 °C point's shape (--shape" in err
        return
    assert "is not shared here" not in err  # the lifted cap bends no ratio
    assert (cold.m, cold.n) == pytest.approx((warm.m, warm.n), abs=1e-5)

    def ratio(p):
        return (p.r_df * p.c_df) ** (1 / p.n) / (p.r_ct * p.c_dl) ** (1 / p.m)

    if shape == "orders-ratio":
        assert ratio(cold) == pytest.approx(ratio(warm), rel=1e-4)
    assert cold.r_ohm > 1.5 * warm.r_ohm


def test_a_fitted_exchange_current_rising_in_the_cold_is_named() -> None:
    """i0 0.31 A at -20 °C above 0.05 A at -10 °C (the Panasonic HPPC fit's): one notice naming both;
    a linear placeholder (i0 at the search's upper bound) and a falling pair say nothing."""
    from service.cell.fitting import LINEAR_I0_A
    from service.cell.profile import ParameterPoint
    from service.characterisation.characterise import (
        FitReport,
        say_exchange_current_rising_in_the_cold,
    )

    def point(t: float, i0: float | None) -> ParameterPoint:
        return ParameterPoint(temp_c=t, r_ohm=0.5, r_ct=0.05, c_dl=10.0, m=1.0, r_df=0.1, c_df=1000.0, n=1.0, i0_a=i0)

    rep = FitReport(quiet=True)
    say_exchange_current_rising_in_the_cold(rep, {-20.0: point(-20.0, 0.31), -10.0: point(-10.0, 0.05),
                                                  0.0: point(0.0, 0.11), 25.0: point(25.0, LINEAR_I0_A)})
    assert len(rep.lines) == 1
    assert "i0 is 0.31 A at -20 °C but 0.05 A at -10 °C" in rep.lines[0]
    rep = FitReport(quiet=True)
    say_exchange_current_rising_in_the_cold(rep, {0.0: point(0.0, 0.11), 10.0: point(10.0, 0.40),
                                                  25.0: point(25.0, None)})
    assert rep.lines == []


def test_a_small_cells_resistances_are_within_the_search() -> None:
    """A 0.1 Ah cell has resistances over the 1 Ω the bounds end at for the cells they were set on
    (resistance x capacity as a 2 Ah cell's): the search widens by the capacity ratio and finds them."""
    scale = 80.0  # the 2 Ah point's resistances x 80 on a 0.1 Ah cell: R_ohm 2.4 Ω, R·Q 4x the 2 Ah cell's
    small = TRUE.model_copy(update={"r_ohm": TRUE.r_ohm * scale, "r_ct": TRUE.r_ct * scale, "c_dl": TRUE.c_dl / scale,
                                    "r_df": TRUE.r_df * scale, "c_df": TRUE.c_df / scale})
    assert small.r_ohm > math.exp(BOUNDS["ln_r_ohm"][1])
    n, cap = 2400, 0.1
    t = np.arange(n, dtype=float)
    i = pulse_current(n, cap, 1)
    temp = np.full(n, 25.0)
    cell = CellProfile(capacity_ah=cap, ocv=nmc_like_ocv(), parameters=[small])
    v, _ = simulate(cell, t, i, temp, 0.95)
    v = v + np.random.default_rng(2).normal(0, 0.001, n)
    res = fit_parameters(cell.model_copy(update={"parameters": [TRUE]}), [FitSegment(t, i, v, temp, soc0=0.95)],
                         max_seconds=120, seed=0, de_maxiter=30)
    assert res.rmse_mv < 1.3  # the noise is 1 mV
    assert res.point.r_ohm == pytest.approx(small.r_ohm, rel=0.1)
    assert not [b for b in res.at_bounds if b.startswith("r_")]


def test_search_bounds_scale_below_the_smallest_cell_they_were_set_on() -> None:
    kinetics = KINETICS_BOUNDS["ln_i0_a"]
    for cap in (BOUNDS_MIN_CAPACITY_AH, 2.9, 50.0):  # as set, for every cell that size or larger
        assert search_bounds(cap) == BOUNDS
        assert list(search_bounds(cap)) == list(BOUNDS)  # the search's coordinate order
        assert kinetics_bounds(cap) == {"ln_i0_a": kinetics}
    ratio = 5.0
    small = search_bounds(BOUNDS_MIN_CAPACITY_AH / ratio)
    assert list(small) == list(BOUNDS)
    for name, (lo, hi) in BOUNDS.items():
        widened = hi + math.log(ratio) if name in ("ln_r_ohm", "ln_r_ct", "ln_r_df") else hi
        assert small[name] == pytest.approx((lo, widened))
    assert kinetics_bounds(BOUNDS_MIN_CAPACITY_AH / ratio)["ln_i0_a"] == pytest.approx(
        (kinetics[0] - math.log(ratio), kinetics[1]))
