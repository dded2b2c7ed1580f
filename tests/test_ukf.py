"""FO-MI-UKF: on a linear model it is a Kalman filter; covariances stay SPD; Cholesky repair."""

from __future__ import annotations

import numpy as np
import pytest

from service.cell.fractional import gl_weights
from service.cell.model import MtsFom
from service.cell.ocv import OcvTable
from service.cell.profile import (
    CellParameters,
    CellProfile,
    HysteresisSpec,
    OcvSpec,
    ParameterPoint,
)
from service.estimators.fomiukf import FoMiUkf
from service.estimators.settings import EstimatorSettings
from service.estimators.sigma_points import merwe_weights, robust_cholesky, sigma_points


def _linear_setup(n_cells: int) -> tuple[OcvTable, CellParameters, EstimatorSettings]:
    """OCV exactly linear in SOC, integer-order branches, no hysteresis."""
    ocv = OcvTable.from_points(np.array([0.0, 1.0]), np.array([3.2, 4.1]))
    prof = CellProfile(
        capacity_ah=2.0,
        ocv=OcvSpec(soc=[0.0, 1.0], ocv_v=[[3.2, 4.1]]),
        parameters=[ParameterPoint(r_ohm=0.02, r_ct=0.01, c_dl=1000.0, m=1.0, r_df=0.02, c_df=15000.0, n=1.0)],
        hysteresis=HysteresisSpec(u_h_max_v=0.0, rate=30.0),
    )
    params = prof.parameters_at(25.0, n_cells=n_cells)
    params.r_ohm = params.r_ohm * np.linspace(0.8, 1.2, n_cells)
    params.capacity_ah = params.capacity_ah * np.linspace(0.9, 1.1, n_cells)
    settings = EstimatorSettings(memory_length=1, innovation_length=1, voltage_noise_v=0.005,
                                 voltage_noise_per_c_v=0.006, current_noise_c=0.01)
    return ocv, params, settings


def _measurement_variance(settings: EstimatorSettings, i: float, capacity_ah: float) -> float:
    """Both noise terms are per C-rate: each cell's own capacity sets its σ in V per A."""
    return settings.voltage_noise_v**2 + (settings.voltage_noise_per_c_v * i / capacity_ah) ** 2


def test_ukf_on_linear_model_equals_kalman_filter() -> None:
    N, T = 3, 200
    ocv, p, s = _linear_setup(N)
    ukf = FoMiUkf(ocv, N, 2, s)
    soc0 = np.array([0.3, 0.5, 0.75])
    ukf.reset(np.ones(N, bool), soc0, 0.1, 0.0)
    weights = gl_weights(p.alpha, s.memory_length)

    # the same model written out as a linear KF: x = [U_ct, U_df, SOC, U_h]
    x = ukf.x.copy()
    P = ukf.P.copy()
    slope = ocv.slope(np.array(0.5))  # constant: the table is linear
    offset = float(ocv.ocv(np.array(0.0)))
    H = np.array([-1.0, -1.0, float(slope), 1.0])

    rng = np.random.default_rng(2)
    true_soc = soc0 + 0.05
    r_adapt = np.zeros(N)
    for k in range(T):
        dt = float(rng.choice([1.0, 1.0, 2.0, 5.0]))
        i = rng.normal(0.5, 2.0, N)
        true_soc = true_soc - i * dt / (3600 * p.capacity_ah)
        v = offset + slope * true_soc - p.r_ohm * i - 0.03 * np.tanh(i) + rng.normal(0, 0.004, N)

        ukf.predict(dt, i, p, weights)
        ukf.update(v, i, np.full(N, 25.0), p, np.ones(N, bool))
        ukf.push_history()

        g = dt / p.c  # order 1: h^1 / C
        den = 1.0 + g / p.r
        a_h = np.exp(-np.abs(p.hyst_rate * i * dt) / (3600 * p.capacity_ah))
        for n in range(N):
            F = np.diag([1 / den[n, 0], 1 / den[n, 1], 1.0, a_h[n]])
            u = np.array([g[n, 0] / den[n, 0] * i[n], g[n, 1] / den[n, 1] * i[n],
                          -i[n] * dt / (3600 * p.capacity_ah[n]), 0.0])
            q = np.array([
                (1e-4 * np.sqrt(dt)) ** 2,
                (1e-4 * np.sqrt(dt)) ** 2,
                (s.current_noise_c * p.capacity_ah[n] * dt / (3600 * p.capacity_ah[n])) ** 2,
                (1e-4 * (1 - a_h[n]) + 1e-6) ** 2,
            ])
            x[n] = F @ x[n] + u
            P[n] = F @ P[n] @ F.T + np.diag(q)
            y = offset + H @ x[n] - p.r_ohm[n] * i[n]
            S = H @ P[n] @ H + _measurement_variance(s, i[n], p.capacity_ah[n])
            e = v[n] - y
            if s.adaptive_noise_samples:
                # covariance matching with the Huber clip, written out (the adaptive UKF)
                S_tot = S + r_adapt[n]
                excess = max(min(e * e, 9.0 * S_tot) - S, 0.0)
                r_adapt[n] = (1 - 1 / s.adaptive_noise_samples) * r_adapt[n] + excess / s.adaptive_noise_samples
                S = S_tot
            K = P[n] @ H / S
            x[n] = x[n] + K * e
            P[n] = P[n] - S * np.outer(K, K)
        np.testing.assert_allclose(ukf.x, x, rtol=1e-9, atol=1e-12, err_msg=f"state at step {k}")
        np.testing.assert_allclose(ukf.P, P, rtol=1e-7, atol=1e-15, err_msg=f"covariance at step {k}")
    assert ukf.repairs == 0
    assert s.adaptive_noise_samples == 0 or np.all(ukf.r_adapt > 0)  # the 0.03 tanh(i) term is model error
    assert np.all(ukf.soc_std > 0)
    # filtering has done something: SOC moved towards the truth from the 5 % error
    assert np.all(np.abs(ukf.soc - true_soc) < 0.03)


def test_unscented_transform_of_linear_map_is_exact() -> None:
    rng = np.random.default_rng(0)
    n = 4
    A = rng.normal(size=(n, n))
    P = A @ A.T + np.eye(n)
    x = rng.normal(size=n)
    F = rng.normal(size=(n, n))
    for alpha, beta, kappa in ((1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (1.0, 0.0, 3.0 - n)):
        wm, wc, gamma = merwe_weights(n, alpha, beta, kappa)
        assert wm.sum() == pytest.approx(1.0)
        L, bad = robust_cholesky(P[None].copy())
        assert not bad.any()
        X = sigma_points(x[None], L, gamma)[0]
        Y = X @ F.T
        y = wm @ Y
        d = Y - y
        np.testing.assert_allclose(y, F @ x, atol=1e-10)
        np.testing.assert_allclose((wc[:, None] * d).T @ d, F @ P @ F.T, rtol=1e-9, atol=1e-10)


def _assert_spd(P: np.ndarray, where: str) -> None:
    scale = np.abs(P).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(P - np.swapaxes(P, 1, 2)) <= 1e-12 * scale), f"asymmetric {where}"
    eig = np.linalg.eigvalsh(P)
    assert np.all(eig > 0), f"not positive definite {where}: min eigenvalue {eig.min()}"


def test_covariance_stays_symmetric_positive_definite(nmc_profile_factory) -> None:
    prof = nmc_profile_factory(hysteresis=HysteresisSpec(u_h_max_v=0.01, rate=60.0))
    N, T = 4, 1500
    s = EstimatorSettings()  # fractional memory, multi-innovation: the real configuration
    rng = np.random.default_rng(9)
    params = prof.parameters_at(25.0, n_cells=N)
    truth = MtsFom(prof, params, np.array([0.95, 0.7, 0.5, 0.3]))
    ukf = FoMiUkf(prof.ocv_table(), N, 2, s)
    ukf.reset(np.ones(N, bool), np.array([0.75, 0.9, 0.3, 0.5]), s.soc_init_std, 0.01)
    weights = gl_weights(params.alpha, s.memory_length)
    temp = np.full(N, 25.0)
    current = np.zeros(N)
    for k in range(T):
        if k % 20 == 0:  # random pulses, both signs, some rests
            current = rng.choice([-2.0, -1.0, 0.0, 0.0, 1.0, 2.0, 4.0], N) * rng.uniform(0.5, 1.0, N)
        dt = float(rng.choice([1.0, 1.0, 1.0, 0.5, 3.0]))
        v = truth.step(dt, current, temp) + rng.normal(0, 0.003, N)
        ukf.predict(dt, current, params, weights)
        _assert_spd(ukf.P, f"after predict, step {k}")
        ukf.update(v, current, temp, params, rng.random(N) > 0.05)
        _assert_spd(ukf.P, f"after update, step {k}")
        ukf.push_history()
    assert ukf.repairs == 0
    assert np.all(np.abs(ukf.soc - truth.soc) < 0.05)


def test_robust_cholesky_repairs_non_pd_matrices() -> None:
    rng = np.random.default_rng(4)
    A = rng.normal(size=(4, 4))
    good = A @ A.T + 0.1 * np.eye(4)
    indefinite = good.copy()
    indefinite[0, 1] = indefinite[1, 0] = 10.0 * np.sqrt(good[0, 0] * good[1, 1])
    singular = np.diag([1.0, 0.0, 2.0, 3.0])
    asym = good.copy()
    asym[0, 3] += 1e-3  # slightly asymmetric: symmetrised, not a repair
    batch = np.stack([good, indefinite, singular, asym])
    L, bad = robust_cholesky(batch.copy())
    np.testing.assert_array_equal(bad, [False, True, True, False])
    assert np.all(np.isfinite(L))
    assert np.allclose(np.triu(L, 1), 0.0)
    rebuilt = L @ np.swapaxes(L, 1, 2)
    np.testing.assert_allclose(rebuilt[0], good, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rebuilt[3], 0.5 * (asym + asym.T), rtol=1e-12, atol=1e-12)
    for k in (1, 2):
        eig = np.linalg.eigvalsh(rebuilt[k])
        assert eig.min() > 0
        # the repair clips eigenvalues, it keeps the eigenvectors and positive eigenvalues
        w, v = np.linalg.eigh(0.5 * (batch[k] + batch[k].T))
        expected = (v * np.maximum(w, 1e-12)) @ v.T
        np.testing.assert_allclose(rebuilt[k], expected, atol=1e-9)


def test_robust_cholesky_alone_does_not_need_repair_for_pd() -> None:
    P = np.tile(np.diag([1e-4, 1e-4, 0.04, 1e-6]), (3, 1, 1))
    L, bad = robust_cholesky(P)
    assert not bad.any()
    np.testing.assert_allclose(L @ np.swapaxes(L, 1, 2), P, rtol=1e-14)


def test_robust_cholesky_writes_the_repair_back() -> None:
    P = np.array([np.eye(3), np.diag([1.0, -0.5, 2.0])])
    robust_cholesky(P)
    assert np.linalg.eigvalsh(P[1]).min() > 0


def test_ukf_covariance_is_repaired_after_an_indefinite_one(nmc_profile: CellProfile) -> None:
    s = EstimatorSettings()
    ukf = FoMiUkf(nmc_profile.ocv_table(), 1, 2, s)
    ukf.reset(np.ones(1, bool), np.array([0.5]), 0.05, 0.0)
    ukf.P[0, 0, 1] = ukf.P[0, 1, 0] = 2e-4  # |ρ| = 2: indefinite
    p = nmc_profile.parameters_at(25.0, n_cells=1)
    w = gl_weights(p.alpha, s.memory_length)
    for _ in range(3):
        ukf.predict(1.0, np.array([1.0]), p, w)
        ukf.update(np.array([3.7]), np.array([1.0]), np.array([25.0]), p, np.ones(1, bool))
        ukf.push_history()
    assert ukf.repairs >= 1
    assert np.linalg.eigvalsh(ukf.P[0]).min() > 0


@pytest.mark.parametrize("window", [1, 4])
def test_single_innovation_posterior_kept_for_the_identifier(nmc_profile, window: int) -> None:
    """With a multi-innovation window the state takes Σγ_i K_i e_i, but the fast identifier's
    Table-1 sensitivity assumes x+ = x- + K e of this sample: that posterior is kept apart."""
    N = 3
    s = EstimatorSettings(innovation_length=window)
    params = nmc_profile.parameters_at(25.0, n_cells=N)
    truth = MtsFom(nmc_profile, params, np.array([0.9, 0.6, 0.3]))
    ukf = FoMiUkf(nmc_profile.ocv_table(), N, 2, s)
    ukf.reset(np.ones(N, bool), np.array([0.8, 0.7, 0.4]), s.soc_init_std, 0.0)
    weights = gl_weights(params.alpha, s.memory_length)
    temp = np.full(N, 25.0)
    rng = np.random.default_rng(3)
    differs = False
    for k in range(60):
        current = np.full(N, 2.0 if (k // 7) % 2 else -1.0)
        v = truth.step(1.0, current, temp) + rng.normal(0, 0.002, N)
        ukf.predict(1.0, current, params, weights)
        prior = ukf.x.copy()
        ukf.update(v, current, temp, params, np.ones(N, bool))
        expected = prior + ukf.gain * ukf.innovation[:, None]
        expected[:, ukf.i_soc] = np.clip(expected[:, ukf.i_soc], 0.0, 1.0)
        np.testing.assert_allclose(ukf.x_single, expected, rtol=0, atol=1e-12)
        differs |= not np.allclose(ukf.x_single, ukf.x)
        ukf.push_history()
    assert differs == (window > 1)
