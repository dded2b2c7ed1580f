"""Grünwald–Letnikov CPE branches: weights, the integer-order limit, memory, broadcasting."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.special import binom

from service.cell.fractional import cpe_gain, cpe_step, gl_weights, push_history


@pytest.mark.parametrize("alpha", [0.1, 0.35, 0.5, 0.7, 0.8, 0.95, 1.0, 1.5])
def test_gl_weights_match_closed_form(alpha: float) -> None:
    L = 40
    j = np.arange(L + 1)
    expected = (-1.0) ** j * binom(alpha, j)
    w = gl_weights(alpha, L)
    assert w.shape == (L + 1,)
    np.testing.assert_allclose(w, expected, rtol=1e-12, atol=1e-15)


def test_gl_weights_properties_for_fractional_orders() -> None:
    alpha = np.array([0.3, 0.6, 0.9])
    w = gl_weights(alpha, 2000)
    assert np.all(w[:, 0] == 1.0)
    np.testing.assert_allclose(w[:, 1], -alpha)
    # for 0 < α < 1 every weight after the first is negative and they shrink in size
    assert np.all(w[:, 1:] < 0)
    assert np.all(np.diff(np.abs(w[:, 1:]), axis=-1) < 0)
    # Σ_j w_j = (1-1)^α = 0: the partial sums approach zero from above
    partial = np.cumsum(w, axis=-1)
    assert np.all(partial > 0)
    assert np.all(np.diff(partial, axis=-1) < 0)
    assert np.all(partial[:, -1] < 0.1)


def test_gl_weights_broadcast_over_any_alpha_shape() -> None:
    alpha = np.array([[0.5, 0.8, 1.0], [0.3, 0.7, 0.9]])
    w = gl_weights(alpha, 7)
    assert w.shape == (2, 3, 8)
    for idx in np.ndindex(alpha.shape):
        np.testing.assert_array_equal(w[idx], gl_weights(float(alpha[idx]), 7))


def test_order_one_weights_are_first_difference() -> None:
    w = gl_weights(1.0, 16)
    np.testing.assert_array_equal(w[:2], [1.0, -1.0])
    assert np.all(w[2:] == 0.0)


def _run_branch(current: np.ndarray, dt: np.ndarray, r: float, c: float, alpha: float, L: int) -> np.ndarray:
    hist = np.zeros((1, L))
    w = gl_weights(np.array([alpha]), L)
    out = np.empty(current.size)
    for k in range(current.size):
        u = cpe_step(hist, np.array([current[k]]), dt[k], np.array([r]), np.array([c]), np.array([alpha]), w)
        push_history(hist, u)
        out[k] = u[0]
    return out


@pytest.mark.parametrize("memory_length", [1, 16])
def test_order_one_is_backward_euler_rc(memory_length: int) -> None:
    rng = np.random.default_rng(1)
    n = 300
    current = rng.normal(0.0, 2.0, n)
    dt = rng.uniform(0.2, 5.0, n)  # non-uniform steps: h is the actual interval
    r, c = 0.01, 800.0
    u = _run_branch(current, dt, r, c, 1.0, memory_length)
    # backward Euler of C dU/dt = I - U/R
    ref = np.empty(n)
    prev = 0.0
    for k in range(n):
        prev = (prev + dt[k] / c * current[k]) / (1.0 + dt[k] / (r * c))
        ref[k] = prev
    np.testing.assert_allclose(u, ref, rtol=1e-12, atol=1e-15)


def test_order_one_converges_to_exact_exponential() -> None:
    r, c, i0 = 0.02, 500.0, 3.0
    tau = r * c  # 10 s
    errors = []
    for dt in (tau / 10, tau / 100, tau / 1000):
        n = round(3 * tau / dt)
        u = _run_branch(np.full(n, i0), np.full(n, dt), r, c, 1.0, 1)
        t = dt * np.arange(1, n + 1)
        exact = i0 * r * (1.0 - np.exp(-t / tau))
        errors.append(np.max(np.abs(u - exact)))
    # first-order method: error shrinks ~10x per 10x smaller step
    assert errors[0] > errors[1] > errors[2]
    for coarse, fine in itertools.pairwise(errors):
        assert 5.0 < coarse / fine < 20.0
    assert errors[-1] < 1e-3 * i0 * r


def test_gain_uses_step_to_the_power_alpha() -> None:
    g = cpe_gain(np.array([2.0, 2.0]), np.array([100.0, 100.0]), np.array([1.0, 0.5]))
    np.testing.assert_allclose(g, [2.0 / 100.0, np.sqrt(2.0) / 100.0])


def test_memory_effect_only_for_fractional_order() -> None:
    """Two histories with the same last voltage but different older ones: the next
    step differs for α < 1 (older samples matter) and is identical for α = 1."""
    L = 16
    h_a = np.zeros((1, L))
    h_b = np.zeros((1, L))
    h_a[0, 0] = h_b[0, 0] = 0.05
    h_b[0, 1:] = 0.08
    args = (np.array([1.0]), 1.0, np.array([0.01]), np.array([600.0]))
    for alpha, differs in ((0.6, True), (0.9, True), (1.0, False)):
        a = np.array([alpha])
        w = gl_weights(a, L)
        ua = cpe_step(h_a, *args, a, w)
        ub = cpe_step(h_b, *args, a, w)
        assert bool(abs(ua[0] - ub[0]) > 1e-6) is differs, alpha


def test_fractional_relaxation_depends_on_memory_length() -> None:
    """After a pulse, a fractional branch's relaxation depends on how much history is
    kept; an integer-order branch's does not."""
    current = np.concatenate([np.full(60, 2.0), np.zeros(120)])
    dt = np.ones(current.size)
    for alpha, same in ((0.7, False), (1.0, True)):
        short = _run_branch(current, dt, 0.02, 300.0, alpha, 4)
        long = _run_branch(current, dt, 0.02, 300.0, alpha, 64)
        assert bool(np.allclose(short, long, rtol=1e-12, atol=1e-15)) is same
    # and with the long memory, a fractional branch relaxes with a heavier tail than
    # its first step suggests: the late decay per step is slower than the early one
    frac = _run_branch(current, dt, 0.02, 300.0, 0.7, 64)[60:]
    early = frac[1] / frac[0]
    late = frac[100] / frac[99]
    assert 0 < early < late < 1


def test_cpe_step_broadcasts_over_cells_and_branches() -> None:
    rng = np.random.default_rng(7)
    N, B, L = 5, 3, 12
    hist = rng.normal(0.0, 0.02, (N, B, L))
    current = rng.normal(0.0, 3.0, N)
    r = rng.uniform(0.005, 0.05, (N, B))
    c = rng.uniform(100.0, 5000.0, (N, B))
    alpha = rng.uniform(0.4, 1.0, (N, B))
    w = gl_weights(alpha, L)
    u = cpe_step(hist, current[:, None], 2.0, r, c, alpha, w)
    assert u.shape == (N, B)
    for n in range(N):
        for b in range(B):
            single = cpe_step(hist[n, b][None], current[n : n + 1], 2.0, r[n, b : b + 1], c[n, b : b + 1],
                              alpha[n, b : b + 1], w[n, b][None])
            assert u[n, b] == pytest.approx(single[0], rel=1e-13, abs=1e-16)
            # and against the formula written out
            g = 2.0 ** alpha[n, b] / c[n, b]
            mem = np.dot(w[n, b, 1:], hist[n, b])
            assert u[n, b] == pytest.approx((g * current[n] - mem) / (1 + g / r[n, b]), rel=1e-12)
    # a per-cell step (dt of shape [N, 1]) broadcasts too
    dt = rng.uniform(0.5, 3.0, (N, 1))
    u2 = cpe_step(hist, current[:, None], dt, r, c, alpha, w)
    for n in range(N):
        np.testing.assert_allclose(u2[n], cpe_step(hist[n], current[n], float(dt[n, 0]), r[n], c[n], alpha[n], w[n]),
                                   rtol=1e-13)


def test_push_history_shifts_newest_first() -> None:
    hist = np.arange(12, dtype=float).reshape(2, 1, 6)
    before = hist.copy()
    push_history(hist, np.array([[100.0], [200.0]]))
    np.testing.assert_array_equal(hist[..., 0], [[100.0], [200.0]])
    np.testing.assert_array_equal(hist[..., 1:], before[..., :-1])
