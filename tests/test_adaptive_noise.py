"""Covariance matching of the measurement noise (service.estimators.adaptive_noise)."""

from __future__ import annotations

import numpy as np

from service.estimators.adaptive_noise import ADAPT_CLIP, N_SHAPE_MOMENTS, AdaptiveNoise


def _feed(noise: AdaptiveNoise, steps: int, rest_var: float, load_coeff: float, seed: int = 0) -> np.ndarray:
    """Innovations whose variance beyond the predicted spread is ``rest_var + load_coeff·φ``."""
    rng = np.random.default_rng(seed)
    n = noise.moments.shape[0]
    s = np.full(n, 1e-6)  # predicted spread (1 mV)²
    for _ in range(steps):
        # a drive: half the samples at rest, the rest under a load of varying size
        load = rng.random(n) < 0.5
        phi = np.where(load, rng.uniform(0.01, 0.2, n) ** 2, 0.0)  # (|I|·R)², V²
        var = s + rest_var + load_coeff * phi
        noise.match(rng.normal(0.0, np.sqrt(var)), s, phi)
    return s


def test_uniform_shape_is_the_one_variance_rule() -> None:
    rng = np.random.default_rng(1)
    noise = AdaptiveNoise(3, samples=50, shape="uniform")
    r = np.zeros(3)
    for _ in range(400):
        e = rng.normal(0.0, 0.01, 3)
        s = np.full(3, 2e-5)
        phi = rng.uniform(0.0, 0.01, 3)
        s_tot = noise.match(e, s, phi)
        # the rule written out: clipped excess, exponentially averaged
        np.testing.assert_allclose(s_tot, s + r, rtol=1e-12)
        excess = np.maximum(np.minimum(e * e, ADAPT_CLIP**2 * (s + r)) - s, 0.0)
        r = (1 - 1 / 50) * r + excess / 50
    a, c = noise.coefficients()
    np.testing.assert_allclose(a, r, rtol=1e-12)
    assert np.all(c == 0.0)


def test_load_shape_separates_rest_and_load_error() -> None:
    # model error only under load: the rests must keep a small variance
    noise = AdaptiveNoise(4, samples=300, shape="load")
    _feed(noise, 6000, rest_var=0.0, load_coeff=0.04)  # 20 % of the overpotential
    a, c = noise.coefficients()
    # the load error is (0.2 · up to 200 mV)²: the rests keep under (3 mV)², a few % of it
    assert np.all(a < (3.0e-3) ** 2), a
    assert np.all(np.abs(c - 0.04) < 0.015), c
    # while the one-variance rule spreads the load error over the rests too
    uniform = AdaptiveNoise(4, samples=300, shape="uniform")
    _feed(uniform, 6000, rest_var=0.0, load_coeff=0.04)
    assert np.all(uniform.extra(np.zeros(4)) > 10 * np.mean(noise.extra(np.zeros(4))))


def test_load_shape_finds_a_rest_error_too() -> None:
    noise = AdaptiveNoise(2, samples=300, shape="load")
    _feed(noise, 6000, rest_var=(3e-3) ** 2, load_coeff=0.0, seed=3)
    a, c = noise.coefficients()
    assert np.all(np.abs(np.sqrt(a) - 3e-3) < 0.6e-3), np.sqrt(a)
    assert np.all(c < 0.01), c  # no load term invented


def test_load_shape_without_spread_in_load_falls_back_to_one_variance() -> None:
    noise = AdaptiveNoise(1, samples=100, shape="load")
    rng = np.random.default_rng(4)
    for _ in range(500):  # constant current: φ never varies, (a, c) not determined
        noise.match(rng.normal(0.0, 0.01, 1), np.full(1, 1e-6), np.full(1, 0.01))
    a, c = noise.coefficients()
    assert c[0] == 0.0 and a[0] == noise.moments[0, 3]


def test_an_outlier_cannot_buy_itself_a_large_variance() -> None:
    noise = AdaptiveNoise(1, samples=10, shape="load")
    s = np.full(1, 1e-6)
    noise.match(np.array([5.0]), s, np.array([0.0]))  # a 5 V innovation
    assert noise.moments[0, 3] <= ADAPT_CLIP**2 * 1e-6 / 10 + 1e-15


def test_only_updated_cells_move() -> None:
    noise = AdaptiveNoise(2, samples=10, shape="load")
    noise.match(np.array([0.1, 0.1]), np.full(2, 1e-6), np.array([0.01, 0.01]), np.array([True, False]))
    assert np.any(noise.moments[0] != 0.0) and np.all(noise.moments[1] == 0.0)
    noise.reset(np.array([True, False]))
    assert np.all(noise.moments == 0.0)


def _ar1(noise: AdaptiveNoise, rho: np.ndarray, steps: int, sigma: float = 0.01, seed: int = 5) -> list[np.ndarray]:
    """Feed innovations of lag-1 autocorrelation ``rho`` (per cell) and spread ``sigma``; returns
    each step's ``S + f·R_extra``."""
    rng = np.random.default_rng(seed)
    e = np.zeros(rho.shape)
    s = np.full(rho.shape, 1e-6)
    out = []
    for _ in range(steps):
        e = rho * e + np.sqrt(1.0 - rho * rho) * rng.normal(0.0, sigma, rho.shape)
        out.append(noise.match(e, s, np.zeros_like(e)))
    return out


def test_inflation_is_the_ar1_variance_inflation_factor() -> None:
    rho = np.array([0.0, 0.5, 0.9])
    noise = AdaptiveNoise(3, samples=300, correlation_cap=1000.0)
    _ar1(noise, rho, 6000)
    # (1+ρ)/(1-ρ) = 1, 3, 19; the exponentially weighted ρ over ~300 samples scatters by ~0.03-0.06
    np.testing.assert_allclose(noise.inflation(), (1 + rho) / (1 - rho), rtol=0.35)
    assert noise.inflation()[0] < 1.3
    s_tot = noise.match(np.zeros(3), np.full(3, 1e-6), np.zeros(3), update=False)
    np.testing.assert_allclose(s_tot, 1e-6 + noise.inflation() * noise.extra(np.zeros(3)), rtol=1e-12)


def test_the_cap_bounds_the_factor_and_one_turns_it_off() -> None:
    rho = np.full(2, 0.95)  # a factor of 39 uncapped
    capped, off = AdaptiveNoise(2, 300, correlation_cap=10.0), AdaptiveNoise(2, 300)
    with_cap, without = _ar1(capped, rho, 3000), _ar1(off, rho, 3000)
    np.testing.assert_allclose(capped.inflation(), 10.0)
    assert off.inflation() == 1.0
    # the factor scales only what is returned: the learned variance is the same either way
    np.testing.assert_array_equal(capped.moments[:, :N_SHAPE_MOMENTS], off.moments[:, :N_SHAPE_MOMENTS])
    s = 1e-6
    np.testing.assert_allclose(with_cap[-1] - s, 10.0 * (without[-1] - s), rtol=1e-9)


def test_a_fit_without_model_error_is_not_slowed_however_correlated() -> None:
    # innovations inside the predicted spread: nothing learned, so nothing inflated
    noise = AdaptiveNoise(1, samples=300, correlation_cap=30.0)
    s_tot = _ar1(noise, np.array([0.95]), 2000, sigma=1e-4)
    assert noise.inflation()[0] > 20
    np.testing.assert_allclose(s_tot[-1], 1e-6, rtol=0.05)
