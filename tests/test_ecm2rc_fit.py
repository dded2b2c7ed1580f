"""The textbook 2-RC characterisation recovers the model it was simulated with, keeps its
OCV monotone, shrugs off outliers, and is what the ``ecm2rc-ekf`` baseline runs on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.cell.coulomb import coulomb_soc
from service.cell.fitting import FitSegment
from service.cell.ocv import GRID_POINTS, OcvTable, flat_share
from service.cell.profile import CellProfile, Ecm2RcPoint, Ecm2RcSpec, OcvSpec, ParameterPoint
from service.characterisation.characterise import (
    ECM_TOLERANCE,
    POOR_FIT_MV,
    FitQualityError,
    FitReport,
    TemperatureFit,
    check_fit_quality,
    ecm_start_point,
    say_flat_joint_ocv,
)
from service.characterisation.ecm2rc_fit import (
    R_MAX_OHM,
    TAU1_BOUNDS_S,
    fit_ecm2rc,
    r_max_ohm,
    simulate_ecm2rc,
)
from service.estimators.ecm2rc_ekf import Ecm2RcEkf, ecm_parameters
from service.recording import Recording

CAPACITY_AH = 2.0
TRUE = {"r0": 0.025, "r1": 0.012, "tau1_s": 8.0, "r2": 0.018, "tau2_s": 150.0}


def ocv_curve(soc: np.ndarray) -> np.ndarray:
    return 3.3 + 0.75 * soc + 0.12 * np.tanh((soc - 0.08) / 0.05) - 0.04 * np.exp(-((soc - 0.55) / 0.1) ** 2)


def drive(n: int, seed: int) -> np.ndarray:
    """Steps between -0.5C and 2C with rests, net discharge, starting at rest."""
    rng = np.random.default_rng(seed)
    out: list[float] = []
    while len(out) < n:
        level = rng.choice([2.0, 1.5, 1.0, 0.5, 0.0, 0.0, -0.5]) * CAPACITY_AH
        out += [level] * int(rng.integers(10, 120))
    cur = np.array(out[:n])
    cur[:60] = 0.0
    return cur


def segment(n: int = 5000, seed: int = 0, noise_v: float = 0.001, soc0: float = 0.95) -> FitSegment:
    t = np.arange(n, dtype=float)
    cur = drive(n, seed)
    grid = np.linspace(0, 1, 201)
    base = FitSegment(t, cur, np.zeros(n), np.full(n, 25.0), soc0)
    v = simulate_ecm2rc(base, CAPACITY_AH, grid, ocv_curve(grid), **TRUE)
    v = v + np.random.default_rng(seed + 100).normal(0.0, noise_v, n)
    return FitSegment(t, cur, v, np.full(n, 25.0), soc0)


def test_recovers_parameters_with_a_known_ocv():
    grid = np.linspace(0, 1, 201)
    fit = fit_ecm2rc([segment()], CAPACITY_AH, ocv_soc=grid, ocv_v=ocv_curve(grid))
    assert fit.r0 == pytest.approx(TRUE["r0"], rel=0.03)
    assert fit.r1 == pytest.approx(TRUE["r1"], rel=0.15)
    assert fit.r2 == pytest.approx(TRUE["r2"], rel=0.15)
    assert fit.tau1_s == pytest.approx(TRUE["tau1_s"], rel=0.25)
    assert fit.tau2_s == pytest.approx(TRUE["tau2_s"], rel=0.25)
    assert fit.rmse_mv < 1.5
    assert fit.at_bounds() == []


def test_a_small_cells_resistances_above_the_large_cell_bound_are_recovered():
    """A 0.05 Ah cell's resistances are ~40 x a 2 Ah cell's: R0 3 Ω lies above R_MAX_OHM, which a
    cell this small raises (as the fractional fit's bounds), so the fit recovers it, not the bound."""
    cap, scale = 0.05, 120.0
    true = {"r0": TRUE["r0"] * scale, "r1": TRUE["r1"] * scale, "tau1_s": TRUE["tau1_s"],
            "r2": TRUE["r2"] * scale, "tau2_s": TRUE["tau2_s"]}
    assert true["r0"] > R_MAX_OHM and r_max_ohm(cap) > true["r2"]
    assert r_max_ohm(CAPACITY_AH) == r_max_ohm(0.85) == R_MAX_OHM
    n = 5000
    t = np.arange(n, dtype=float)
    cur = drive(n, 0) * cap / CAPACITY_AH
    grid = np.linspace(0, 1, 201)
    v = simulate_ecm2rc(FitSegment(t, cur, np.zeros(n), np.full(n, 25.0), 0.95), cap, grid, ocv_curve(grid), **true)
    v = v + np.random.default_rng(100).normal(0.0, 0.001, n)
    fit = fit_ecm2rc([FitSegment(t, cur, v, np.full(n, 25.0), 0.95)], cap, ocv_soc=grid, ocv_v=ocv_curve(grid))
    assert fit.r0 == pytest.approx(true["r0"], rel=0.03)
    assert fit.rmse_mv < 1.5
    assert fit.at_bounds() == []


def test_joint_ocv_is_monotone_and_close_where_the_data_went():
    segs = [segment(6000, seed=s, soc0=0.98 - 0.3 * s) for s in range(3)]
    fit = fit_ecm2rc(segs, CAPACITY_AH)
    assert np.all(np.diff(fit.ocv_v) >= 0.0)
    visited = (fit.ocv_soc > 0.2) & (fit.ocv_soc < 0.95)
    err = fit.ocv_v[visited] - ocv_curve(fit.ocv_soc[visited])
    assert np.max(np.abs(err)) < 0.012
    assert fit.r0 == pytest.approx(TRUE["r0"], rel=0.1)
    assert fit.rmse_mv < 3.0


def test_the_smoothing_weight_smooths_the_joint_ocv():
    """A larger weight on the second-difference penalty leaves a joint OCV with less curvature
    (``socd fit --ocv-smoothing``), still monotone; the default stays close to the true curve."""
    segs = [segment(6000, seed=s, noise_v=0.004, soc0=0.98 - 0.3 * s) for s in range(3)]
    rough = {}
    for w in (0.01, 10.0):
        fit = fit_ecm2rc(segs, CAPACITY_AH, smooth_weight=w)
        assert np.all(np.diff(fit.ocv_v) >= 0.0)
        visited = (fit.ocv_soc > 0.2) & (fit.ocv_soc < 0.95)
        rough[w] = float(np.sum(np.diff(fit.ocv_v[visited], 2) ** 2))
    assert rough[10.0] < 0.5 * rough[0.01]


def test_huber_weights_hold_against_outliers():
    seg = segment()
    v = seg.voltage_v.copy()
    rng = np.random.default_rng(7)
    bad = rng.choice(v.size, size=v.size // 50, replace=False)
    v[bad] += rng.choice([-0.5, 0.5], size=bad.size)  # 2 % of samples off by half a volt
    grid = np.linspace(0, 1, 201)
    fit = fit_ecm2rc([FitSegment(seg.time_s, seg.current_a, v, seg.temperature_c, seg.soc0)], CAPACITY_AH,
                     ocv_soc=grid, ocv_v=ocv_curve(grid))
    assert fit.r0 == pytest.approx(TRUE["r0"], rel=0.05)
    assert fit.tau1_s >= TAU1_BOUNDS_S[0]


def test_ekf_runs_on_the_textbook_spec_not_the_fractional_parameters():
    grid = np.linspace(0, 1, 201)
    spec = Ecm2RcSpec(ocv=OcvSpec(soc=grid.tolist(), ocv_v=[ocv_curve(grid).tolist()]),
                      points=[Ecm2RcPoint(temp_c=25.0, **TRUE)])
    wrong = ParameterPoint(r_ohm=0.2, r_ct=0.1, c_dl=10.0, m=0.5, r_df=0.3, c_df=10.0, n=0.5)
    flat_ocv = OcvSpec(soc=[0.0, 1.0], ocv_v=[[3.6, 3.7]])
    prof = CellProfile(capacity_ah=CAPACITY_AH, ocv=flat_ocv, parameters=[wrong], ecm2rc=spec)
    par = ecm_parameters(prof, np.array([25.0]))
    assert par["r0"][0] == pytest.approx(TRUE["r0"])
    assert par["tau"][0, 1] == pytest.approx(TRUE["tau2_s"])
    seg = segment(4000, noise_v=0.002)
    truth = coulomb_soc(seg.time_s, seg.current_a, CAPACITY_AH, seg.soc0)
    rec = Recording(path=Path("sim.csv"), time_s=seg.time_s, current_a=seg.current_a, voltage_v=seg.voltage_v,
                    temperature_c=seg.temperature_c)
    trace = Ecm2RcEkf().run(rec, prof, soc0=seg.soc0 - 0.2)
    assert np.sqrt(np.mean((trace.soc[1000:] - truth[1000:]) ** 2)) < 0.01
    # without the spec the same filter reads the (wrong) fractional parameters and flat OCV
    plain = Ecm2RcEkf().run(rec, prof.model_copy(update={"ecm2rc": None}), soc0=seg.soc0 - 0.2)
    assert np.sqrt(np.mean((plain.soc[1000:] - truth[1000:]) ** 2)) > 0.05


@pytest.mark.parametrize(("rmse", "ecm", "overpotential", "bad"), [
    (12.0, 11.0, 100.0, False),                     # within the tolerance of the 2-RC fit
    (12.0, 12.0 / (1 + ECM_TOLERANCE[0]) - 1.0, 100.0, True),   # clearly worse than the 2-RC fit
    (POOR_FIT_MV + 1.0, POOR_FIT_MV + 5.0, 60.0, True),       # poor in itself
    # a hard drive in the cold: 90 mV left of a volt of overpotential is a model of it
    (90.0, 93.0, 1000.0, False),
    (650.0, 700.0, 1000.0, True),                   # more than POOR_FIT_SHARE of it left
    (72.6, 76.8, 136.0, False),                     # the PyBaMM LFP cell's US06: 53 % left, a usable profile
    (float("nan"), 10.0, 100.0, True),
])
def test_fit_quality_rule(rmse, ecm, overpotential, bad):
    rep = FitReport(temperatures=[TemperatureFit(temp_c=25.0, rmse_mv=rmse, ecm_rmse_mv=ecm, at_bounds=[],
                                                 source="fractional fit", overpotential_rms_mv=overpotential)])
    if bad:
        with pytest.raises(FitQualityError, match="25 °C"):
            check_fit_quality(rep)
    else:
        check_fit_quality(rep)


@pytest.mark.parametrize("measured", [False, True])
def test_a_refused_fit_names_data_the_user_has_not_given(measured):
    """With the OCV fitted jointly an OCV test would help; with it measured (a table or a test given),
    suggesting one again would send the user for data they already gave: the hint names the dynamics."""
    rep = FitReport(temperatures=[TemperatureFit(temp_c=10.0, rmse_mv=92.6, ecm_rmse_mv=96.8, at_bounds=[],
                                                 source="fractional fit", overpotential_rms_mv=136.0,
                                                 ocv_measured=measured)])
    with pytest.raises(FitQualityError) as err:
        check_fit_quality(rep)
    text = str(err.value)
    assert text.startswith("10 °C: fit RMSE 92.6 mV") and text.endswith("--force writes the profile anyway")
    assert ("an OCV test" in text) is not measured
    assert "first check --capacity-ah" in text  # a wrong capacity fails this way with or without an OCV
    assert ("the OCV there is measured" in text and "96.8 mV" in text and "HPPC" in text) is measured


@pytest.mark.parametrize(("rmse", "simulated", "bad"), [
    (9.6, 9.9, False),   # 11 % above the 2-RC fit's own 8.6 mV, but better than its point as this model reads it
    (11.0, 9.9, True),   # worse than the 2-RC point read the same way
])
def test_fit_quality_holds_the_fit_to_the_2rc_point_simulated_as_it_is(rmse, simulated, bad):
    """The bar is the 2-RC fit's point run through the fractional model's own simulation (the stored
    OCV table, its time step): what the 2-RC fit's own RMSE would be in that simulation. Both fits are
    then read the same way, so a representation loss both suffer does not refuse the fractional one."""
    rep = FitReport(temperatures=[TemperatureFit(temp_c=25.0, rmse_mv=rmse, ecm_rmse_mv=8.6, ecm_simulated_mv=simulated,
                                                 at_bounds=[], source="fractional fit", overpotential_rms_mv=100.0)])
    if bad:
        with pytest.raises(FitQualityError, match=r"9\.9 mV as this model simulates its point; 8\.6 mV its own fit"):
            check_fit_quality(rep)
    else:
        check_fit_quality(rep)


def test_two_rc_point_writes_the_textbook_model_in_the_fractional_form(tmp_path: Path):
    """``research.two_rc_point`` replaces the fractional point by the stored 2-RC one (orders 1,
    C = τ/R), so the fractional model simulates the 2-RC model's voltage; hysteresis goes off."""
    from research.two_rc_point import main as two_rc_point
    from service.cell.profile import HysteresisSpec, load_profile, save_profile
    from service.cell.trajectory import simulate

    grid = np.linspace(0, 1, 201)
    ocv = OcvSpec(soc=grid.tolist(), ocv_v=[ocv_curve(grid).tolist()])
    spec = Ecm2RcSpec(ocv=ocv, points=[Ecm2RcPoint(temp_c=25.0, **TRUE)])
    wrong = ParameterPoint(temp_c=25.0, r_ohm=0.2, r_ct=0.1, c_dl=10.0, m=0.5, r_df=0.3, c_df=10.0, n=0.5)
    src, out = tmp_path / "cell.toml", tmp_path / "cell_2rc.toml"
    save_profile(CellProfile(capacity_ah=CAPACITY_AH, ocv=ocv, parameters=[wrong], ecm2rc=spec,
                             hysteresis=HysteresisSpec(u_h_max_v=0.02, rate=30.0)), src)
    assert two_rc_point([str(src), str(out)]) == 0
    prof = load_profile(out)
    (p,) = prof.parameters
    assert (p.m, p.n, p.r_ohm, p.r_ct, p.r_df) == pytest.approx((1.0, 1.0, TRUE["r0"], TRUE["r1"], TRUE["r2"]))
    assert prof.hysteresis.u_h_max_v == 0.0
    seg = segment(3000, noise_v=0.0)
    v_fo, _ = simulate(prof, seg.time_s, seg.current_a, seg.temperature_c, seg.soc0)
    # the fractional form steps the branches by backward Euler, the 2-RC fit exactly: close, not equal
    assert np.sqrt(np.mean((v_fo - seg.voltage_v) ** 2)) < 1e-3
    assert two_rc_point([str(src), str(tmp_path / "x.toml"), "--temp", "5"]) == 2  # no point there


def test_two_rc_point_with_the_two_rc_ocv_is_the_textbook_ekfs_whole_model(tmp_path: Path):
    """``--ocv two-rc`` also takes the 2-RC fit's OCV row, so the profile holds the model the
    textbook EKF runs; without it the fractional OCV stays."""
    from research.two_rc_point import main as two_rc_point
    from service.cell.profile import load_profile, save_profile

    grid = np.linspace(0, 1, 201)
    frac = OcvSpec(soc=grid.tolist(), ocv_v=[ocv_curve(grid).tolist()])
    own = OcvSpec(soc=grid.tolist(), ocv_v=[(ocv_curve(grid) + 0.015).tolist()])
    spec = Ecm2RcSpec(ocv=own, points=[Ecm2RcPoint(temp_c=25.0, **TRUE)])
    point = ParameterPoint(temp_c=25.0, r_ohm=0.2, r_ct=0.1, c_dl=10.0, m=0.5, r_df=0.3, c_df=10.0, n=0.5)
    src = tmp_path / "cell.toml"
    save_profile(CellProfile(capacity_ah=CAPACITY_AH, ocv=frac, parameters=[point], ecm2rc=spec), src)
    assert two_rc_point([str(src), str(tmp_path / "whole.toml"), "--ocv", "two-rc"]) == 0
    assert two_rc_point([str(src), str(tmp_path / "points.toml")]) == 0
    whole, points = load_profile(tmp_path / "whole.toml"), load_profile(tmp_path / "points.toml")
    assert np.allclose(whole.ocv.ocv_v[0], ocv_curve(grid) + 0.015)
    assert np.allclose(points.ocv.ocv_v[0], ocv_curve(grid))
    assert whole.parameters == points.parameters


def test_flat_share_and_the_fit_notice_for_a_flat_joint_ocv():
    """A monotone row flat over 0.4-0.5 SOC (a joint fit's active bound) is flat over a tenth of SOC,
    and the fit says so per temperature as a notice; a rising row says nothing."""
    grid = np.linspace(0.0, 1.0, GRID_POINTS)
    rising = 3.4 + 0.8 * grid
    flat = np.where(grid < 0.4, rising, np.where(grid <= 0.5, 3.4 + 0.8 * 0.4, rising - 0.08))
    assert flat_share(OcvTable.from_points(grid, rising), 25.0) == 0.0
    assert flat_share(OcvTable.from_points(grid, flat), 25.0) == pytest.approx(0.1, abs=0.01)
    rep = FitReport(echo=lambda _: None)
    say_flat_joint_ocv(rep, grid, {25.0: rising, 0.0: flat})
    assert len(rep.lines) == 1 and "0 °C" in rep.lines[0] and "flat over 10 % of SOC" in rep.lines[0]


@pytest.mark.parametrize("cap_s", [None, 1000.0, 50.0, 2.0])
def test_the_2rc_start_point_keeps_the_diffusion_cap(cap_s: float | None) -> None:
    """The fit keeps the 2-RC start where the search ends worse; that point honours ``--max-tau-df``
    as the search does (it kept τ2 = 400 s under any cap)."""
    ecm = Ecm2RcPoint(temp_c=25.0, r0=0.02, r1=0.01, tau1_s=10.0, r2=0.015, tau2_s=400.0)
    pt = ecm_start_point(ecm, 25.0, max_tau_df_s=cap_s)
    tau_df = (pt.r_df * pt.c_df) ** (1.0 / pt.n)
    assert tau_df == pytest.approx(min(400.0, cap_s or np.inf))
    assert (pt.r_ohm, pt.r_ct, pt.r_df) == (0.02, 0.01, 0.015)


def test_the_fast_solver_gives_the_bounded_solvers_minimiser_on_and_off_a_ceiling():
    """The non-negative solve is the bounded problem's minimiser where no ceiling binds, and a
    solution past a resistance's ceiling goes to the general bounded solver (BVLS)."""
    from scipy.optimize import lsq_linear

    from service.characterisation.ecm2rc_fit import _bounded_lstsq

    rng = np.random.default_rng(4)
    a = rng.normal(size=(12, 6))
    lo = np.array([0.0, 0.0, 0.0, -np.inf, 0.0, 0.0])
    for x_true, ceiling in ((np.array([0.02, 0.01, 0.03, 3.6, 0.1, 0.0]), 2.0),
                            (np.array([2.5, 0.01, 0.03, 3.6, 0.1, 0.2]), 2.0)):
        b = a @ x_true + rng.normal(0.0, 1e-3, 12)
        hi = np.array([ceiling] * 3 + [np.inf] * 3)
        got = _bounded_lstsq(a, b, lo, hi, floor=-5.0)
        want = lsq_linear(a, b, bounds=(lo, hi), method="bvls", tol=1e-12).x
        np.testing.assert_allclose(got, want, atol=1e-9)
        assert np.all(got <= hi + 1e-12) and np.all(got[np.isfinite(lo)] >= -1e-12)
    assert got[0] == pytest.approx(2.0)  # the second case sits on its ceiling


def test_branch_inputs_are_the_exact_recursion_on_regular_gapped_and_jittered_time():
    from service.characterisation.ecm2rc_fit import _branch_inputs_stepwise, _prepare, branch_inputs

    base = segment(600)
    gapped = base.time_s.astype(float).copy()
    gapped[300:] += 45.0  # one logging gap
    jittered = np.cumsum(np.random.default_rng(5).uniform(0.5, 1.5, base.time_s.size))
    taus = np.array([1.0, 8.0, 150.0, 1000.0])
    for t in (base.time_s, gapped, jittered):
        segs = [FitSegment(t, base.current_a, base.voltage_v, base.temperature_c, base.soc0), base]
        prep = _prepare(segs, CAPACITY_AH)
        np.testing.assert_allclose(branch_inputs(prep, taus), _branch_inputs_stepwise(prep, taus), rtol=0, atol=1e-12)
