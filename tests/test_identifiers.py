"""Online parameter identification: recovery on model-simulated data, and bounds under garbage.

The data are simulated by the same MTS-FOM the estimator uses (true parameters in
``conftest.NMC_PARAMETERS``), with 2 mV voltage noise, so any bias comes from the
identifiers themselves.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.cell.fractional import gl_weights
from service.cell.model import MtsFom
from service.estimators.parameter_ekf import (
    ORDER_LIMITS,
    RELATIVE_LIMITS,
    U_DF_LIMITS,
    ParameterEkf,
    branch_step_and_derivatives,
)
from service.estimators.pipeline import PackEstimator, fom_single_scale
from service.estimators.settings import EstimatorSettings
from service.estimators.slow_identifier import SlowIdentifier
from service.recording import load_recording


@pytest.fixture
def truth(nmc_true_parameters) -> dict[str, float]:
    return nmc_true_parameters


def _run(est: PackEstimator, rec, steps: int | None = None, soc0: float | None = None) -> PackEstimator:
    est.start(np.array([rec.soc_true[0] if soc0 is None else soc0]))
    dt = np.diff(rec.time_s, prepend=rec.time_s[0])
    for k in range(len(rec) if steps is None else steps):
        est.step(dt[k], rec.current_a[k], rec.voltage_v[k : k + 1], rec.temperature_c[k : k + 1])
        est.slow_update()
    return est


def _rel(value: np.ndarray, truth: float) -> float:
    return float(abs(value[0] / truth - 1.0))


# -- fast identifier (Zeng Eqs. 11-13, Table 1) -------------------------------------------
def test_branch_derivatives_match_finite_differences() -> None:
    rng = np.random.default_rng(0)
    N, L = 4, 16
    hist = rng.normal(0.0, 0.01, (N, L))
    i = rng.normal(0.0, 3.0, N)
    r = rng.uniform(0.005, 0.03, N)
    c = rng.uniform(200.0, 3000.0, N)
    a = rng.uniform(0.5, 0.95, N)
    _, du_dr, du_dc, du_da = branch_step_and_derivatives(hist, i, 1.0, r, c, a, gl_weights(a, L))

    def step(rr, cc, aa):
        return branch_step_and_derivatives(hist, i, 1.0, rr, cc, aa, gl_weights(aa, L))[0]

    for d, base, fn in (
        (du_dr, r, lambda x: step(x, c, a)),
        (du_dc, c, lambda x: step(r, x, a)),
        (du_da, a, lambda x: step(r, c, x)),
    ):
        h = 1e-6 * base
        fd = (fn(base + h) - fn(base - h)) / (2 * h)
        np.testing.assert_allclose(d, fd, rtol=1e-5, atol=1e-12)


@pytest.mark.parametrize(
    "names, start",
    [
        (["r_ohm", "r_ct"], (1.3, 0.7)),
        (["r_ohm", "r_ct"], (0.7, 1.3)),
        (["r_ohm", "r_ct", "c_dl", "m"], (1.3, 0.7)),
    ],
)
def test_parameter_ekf_recovers_resistances(nmc_recording, nmc_profile_factory, truth, names, start) -> None:
    """Started 30 % off with a prior σ of 30 %, the EKF gets R_ohm within 15 % and R_ct
    within 20 % in 10 minutes of pulses (measured: at most ~3.5 % and ~5 %)."""
    rec = nmc_recording(duration_s=600, seed=1, soc0=0.9)
    true_r_ohm, true_r_ct = truth["r_ohm"], truth["r_ct"]
    prof = nmc_profile_factory(r_ohm=true_r_ohm * start[0], r_ct=true_r_ct * start[1])
    s = EstimatorSettings(slow_identifier=False)
    est = PackEstimator(prof, 1, s)
    est.fast = ParameterEkf(names, 1, est.n_branches + 2, s.param_process_rel, s.voltage_noise_v, init_rel=0.3)
    _run(est, rec)
    p = est.parameters()
    assert _rel(p["r_ohm"], true_r_ohm) < 0.15
    assert _rel(p["r_ct"], true_r_ct) < 0.20
    assert est.reset_count[0] == 0
    assert abs(est.soc[0] - rec.soc_true[-1]) < 0.01


def test_pipeline_fast_identifier_stays_near_truth(nmc_recording, nmc_profile, truth) -> None:
    true_r_ohm, true_r_ct = truth["r_ohm"], truth["r_ct"]
    rec = nmc_recording(duration_s=1500, seed=0, soc0=0.9)
    est = _run(PackEstimator(nmc_profile, 1, EstimatorSettings(slow_identifier=False)), rec)
    p = est.parameters()
    assert _rel(p["r_ohm"], true_r_ohm) < 0.25
    assert _rel(p["r_ct"], true_r_ct) < 0.25


def _identified_spread(rec, profile, settings: EstimatorSettings, noise_v: float) -> tuple[float, PackEstimator]:
    """RMS over the drive's second half of the identified R_ohm and R_ct's relative departure from the
    profile (the truth here), with white noise of σ ``noise_v`` on the voltage the estimator reads."""
    est = PackEstimator(profile, 1, settings)
    est.start(np.array([rec.soc_true[0]]))
    v = rec.voltage_v + np.random.default_rng(7).normal(0.0, noise_v, len(rec))
    dt = np.diff(rec.time_s, prepend=rec.time_s[0])
    dev = []
    for k in range(len(rec)):
        est.step(dt[k], rec.current_a[k], v[k : k + 1], rec.temperature_c[k : k + 1])
        if k >= len(rec) // 2:
            z = est.fast.z[0]
            dev.append([z[est.fast.names.index("r_ohm")] - 1.0, z[est.fast.names.index("r_ct")] - 1.0])
    return float(np.sqrt(np.mean(np.square(dev)))), est


def test_identifier_matches_its_noise_and_then_moves_less_on_it(nmc_recording, nmc_profile) -> None:
    """Voltage error far beyond the identifier's fixed R (30 mV against 10 mV): the matched
    variance learns it and the identified resistances wander less than with the fixed R; on the
    clean recording it learns little and stays near the truth."""
    rec = nmc_recording(duration_s=600, seed=2, soc0=0.9)
    matched = EstimatorSettings(adaptive_noise_samples=300)
    fixed = EstimatorSettings(adaptive_noise_samples=0)
    noisy_matched, est = _identified_spread(rec, nmc_profile, matched, 0.03)
    noisy_fixed, est_fixed = _identified_spread(rec, nmc_profile, fixed, 0.03)
    assert est_fixed.fast.noise is None
    learned = est.fast.noise.extra(np.zeros(1))[0]
    assert learned > (0.01) ** 2
    assert noisy_matched < 0.7 * noisy_fixed
    clean_matched, est_clean = _identified_spread(rec, nmc_profile, matched, 0.0)
    assert est_clean.fast.noise.extra(np.zeros(1))[0] < 0.1 * learned
    assert clean_matched < 0.05


# -- slow identifier (Zeng Eqs. 14-16, Table 2) -----------------------------------------------
def _diffusion_voltage(profile, current: np.ndarray, memory_length: int) -> np.ndarray:
    n = current.size
    model = MtsFom(profile, profile.parameters_at(25.0, n_cells=1), np.array([0.9]), memory_length=memory_length)
    u_df = np.empty(n)
    for k in range(n):
        model.step(1.0 if k else 0.0, current[k : k + 1], np.array([25.0]))
        u_df[k] = model.history[0, 1, 0]
    return u_df


def test_slow_identifier_moves_r_df_toward_truth(nmc_profile, nmc_current, truth) -> None:
    """Fed the true diffusion voltage (+1 mV noise), R_df started 30 % high and 30 % low both
    move toward the truth.  (With the default memory length 16 at 1 s the truncated G-L
    tail dominates U_df's steady state and R_df is barely observable; 128 is used here.)"""
    L, n = 128, 2000
    true_r_df = truth["r_df"]
    current = nmc_current(n, nmc_profile.capacity_ah, seed=1)
    u_df = _diffusion_voltage(nmc_profile, current, memory_length=L)
    meas = u_df + np.random.default_rng(1).normal(0.0, 0.001, n)
    start = np.array([1.3, 0.7])
    nominal_r = true_r_df * start
    c_df = np.full(2, truth["c_df"])
    order = np.full(2, truth["n"])
    slow = SlowIdentifier(2, L, soc_delta=0.005, process_rel=0.02)
    for k in range(n):
        slow.record(1.0 if k else 0.0, np.full(2, current[k]), np.full(2, meas[k]), np.full(2, 2.0))
        slow.update(nominal_r, c_df, order)
    assert slow.updates > 20
    r_df = nominal_r * slow.z[:, 0]
    err0 = np.abs(nominal_r - true_r_df)
    err = np.abs(r_df - true_r_df)
    assert np.all(err < 0.85 * err0), r_df
    assert np.all(np.sign(r_df - true_r_df) == np.sign(nominal_r - true_r_df))  # no overshoot


def test_slow_identifier_waits_for_charge_throughput() -> None:
    slow = SlowIdentifier(1, 16, soc_delta=0.01, process_rel=0.02)
    nom = (np.array([0.02]), np.array([2700.0]), np.array([0.7]))
    for _ in range(100):  # rest: no throughput, never due
        slow.record(1.0, np.zeros(1), np.zeros(1), np.full(1, 2.0))
        assert not slow.update(*nom)
    for k in range(71):  # 1 A for 71 s on 2 Ah = 0.0099 of capacity
        slow.record(1.0, np.ones(1), np.full(1, 0.005), np.full(1, 2.0))
        assert not slow.update(*nom), k
    slow.record(1.0, np.full(1, -2.0), np.full(1, 0.005), np.full(1, 2.0))  # charge counts too
    assert slow.update(*nom)
    assert slow.updates == 1 and slow.start[0] == slow.length and slow.moved[0] == 0  # new interval begins here


def test_pipeline_slow_identifier_moves_r_df_toward_truth(nmc_recording, nmc_profile_factory, truth) -> None:
    true_r_df = truth["r_df"]
    rec = nmc_recording(duration_s=1500, seed=1, soc0=0.9)
    est = _run(PackEstimator(nmc_profile_factory(r_df=1.3 * true_r_df), 1, EstimatorSettings(slow_identifier=True)), rec)
    assert est.slow.updates > 10
    assert abs(est.parameters()["r_df"][0] - true_r_df) < 0.3 * true_r_df


# -- single time scale -------------------------------------------------------------------------
def test_fom_single_scale_runs_and_moves_toward_truth(nmc_recording, nmc_profile_factory, truth) -> None:
    true_r_ohm, true_r_ct = truth["r_ohm"], truth["r_ct"]
    rec = nmc_recording(duration_s=1200, seed=1, soc0=0.9)
    prof = nmc_profile_factory(r_ohm=1.3 * true_r_ohm, r_ct=0.7 * true_r_ct)
    trace = fom_single_scale().run(load_recording(rec.path), prof, 0.7)
    assert set(trace.params) == {"r_ohm", "r_ct", "c_dl", "m", "r_df", "c_df", "n"}
    for name, values in trace.params.items():
        assert values.shape == (len(rec),) and np.all(np.isfinite(values)), name
    nominal = prof.parameters_at(25.0, n_cells=1)
    for name, nom in (("r_ohm", nominal.r_ohm[0]), ("r_ct", nominal.r[0, 0]), ("c_dl", nominal.c[0, 0]),
                      ("r_df", nominal.r[0, 1]), ("c_df", nominal.c[0, 1])):
        ratio = trace.params[name] / nom
        assert np.all((ratio >= RELATIVE_LIMITS[0] - 1e-9) & (ratio <= RELATIVE_LIMITS[1] + 1e-9)), name
    for name in ("m", "n"):
        assert np.all((trace.params[name] >= ORDER_LIMITS[0]) & (trace.params[name] <= ORDER_LIMITS[1]))
    assert abs(trace.params["r_ohm"][-1] - true_r_ohm) < abs(1.3 * true_r_ohm - true_r_ohm)
    err = trace.soc - rec.soc_true
    assert np.sqrt(np.mean(err[600:] ** 2)) < 0.02


# -- bounds under garbage ----------------------------------------------------------------------
def _assert_in_bounds(est: PackEstimator, where: str) -> None:
    nom = est.nominal
    fast, slow = est.fast, est.slow
    if fast is not None:
        assert np.all(np.isfinite(fast.z)) and np.all(np.isfinite(fast.P)), where
        for col, name in enumerate(fast.names):
            z = fast.z[:, col]
            if name in ("m", "n"):
                base = nom.alpha[:, 0 if name == "m" else 1]
                assert np.all((base + z >= ORDER_LIMITS[0] - 1e-12) & (base + z <= ORDER_LIMITS[1] + 1e-12)), (name, where)
            elif name == "u_df":
                assert np.all((z >= U_DF_LIMITS[0]) & (z <= U_DF_LIMITS[1])), where
            else:
                assert np.all((z >= RELATIVE_LIMITS[0]) & (z <= RELATIVE_LIMITS[1])), (name, where)
    if slow is not None:
        assert np.all(np.isfinite(slow.z)), where
        assert np.all((slow.z[:, :2] >= RELATIVE_LIMITS[0]) & (slow.z[:, :2] <= RELATIVE_LIMITS[1])), where
        a = nom.alpha[:, 1] + slow.z[:, 2]
        assert np.all((a >= ORDER_LIMITS[0] - 1e-12) & (a <= ORDER_LIMITS[1] + 1e-12)), where
    p = est.parameters()
    for name, nomv in (("r_ohm", nom.r_ohm), ("r_ct", nom.r[:, 0]), ("c_dl", nom.c[:, 0]),
                       ("r_df", nom.r[:, 1]), ("c_df", nom.c[:, 1])):
        ratio = p[name] / nomv
        assert np.all(np.isfinite(ratio)), (name, where)
        assert np.all((ratio >= RELATIVE_LIMITS[0] - 1e-9) & (ratio <= RELATIVE_LIMITS[1] + 1e-9)), (name, where)
    for name in ("m", "n"):
        assert np.all((p[name] >= ORDER_LIMITS[0]) & (p[name] <= ORDER_LIMITS[1])), (name, where)


@pytest.mark.parametrize("identification", ["multi", "single"])
def test_parameters_stay_in_bounds_with_garbage_voltages(nmc_profile, identification) -> None:
    N, T = 6, 300
    # identify at every step (no SOC-σ gate) and update the slow identifier often
    s = EstimatorSettings(identify_below_soc_std=1.0, slow_soc_delta=0.001)
    est = PackEstimator(nmc_profile, N, s, identification)
    est.start(np.full(N, 0.6))
    rng = np.random.default_rng(3)
    for k in range(T):
        i = rng.normal(0.0, 5.0, N)
        v = rng.uniform(-5.0, 15.0, N)
        v[rng.random(N) < 0.1] = rng.choice([1e6, -1e6, 0.0])
        est.step(1.0, i, v, np.full(N, 25.0))
        est.slow_update()
        _assert_in_bounds(est, f"step {k}")
    assert np.all(np.isfinite(est.soc)) and np.all(np.isfinite(est.soc_std))


def test_slow_identifier_bounds_with_garbage_measurements() -> None:
    N = 4
    slow = SlowIdentifier(N, 16, soc_delta=0.001, process_rel=0.5)
    nom = (np.full(N, 0.02), np.full(N, 2700.0), np.array([0.35, 0.7, 0.9, 0.99]))
    rng = np.random.default_rng(8)
    for k in range(400):
        meas = rng.choice([1e3, -1e3, 50.0, -50.0, 0.0], N)
        meas[rng.random(N) < 0.05] = np.nan
        slow.record(1.0, rng.normal(0.0, 4.0, N), meas, np.full(N, 2.0))
        slow.update(*nom)
        assert np.all(np.isfinite(slow.z)), k
        assert np.all((slow.z[:, :2] >= RELATIVE_LIMITS[0]) & (slow.z[:, :2] <= RELATIVE_LIMITS[1])), k
        a = nom[2] + slow.z[:, 2]
        assert np.all((a >= ORDER_LIMITS[0] - 1e-12) & (a <= ORDER_LIMITS[1] + 1e-12)), k
    assert slow.updates > 50


def test_identifier_prior_is_the_setting_and_a_restart_returns_to_it(nmc_recording, nmc_profile) -> None:
    """`param_init_std_rel` is the resistances' prior σ; after identifying, a restarted cell is back
    at the profile's parameters with that prior, and the other cell keeps what it learned."""
    rec = nmc_recording(duration_s=600, seed=3, soc0=0.9)
    s = EstimatorSettings(param_init_std_rel=0.04)
    est = PackEstimator(nmc_profile, 2, s)
    fast = est.fast
    r = fast.names.index("r_ohm")
    np.testing.assert_allclose(fast.P[:, r, r], 0.04**2)
    est.start(np.full(2, rec.soc_true[0]))
    dt = np.diff(rec.time_s, prepend=rec.time_s[0])
    for k in range(len(rec)):
        est.step(dt[k], rec.current_a[k], np.full(2, rec.voltage_v[k]), np.full(2, rec.temperature_c[k]))
    assert fast.P[0, r, r] < 0.8 * 0.04**2  # it learned
    learned = fast.P[1].copy()
    est.start(np.full(2, rec.soc_true[-1]), cells=np.array([True, False]))
    np.testing.assert_allclose(fast.P[0], fast.P0)
    assert fast.z[0, r] == 1.0
    np.testing.assert_allclose(fast.P[1], learned)
