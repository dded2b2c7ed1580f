"""Grünwald–Letnikov fractional calculus for CPE branches (Zeng Eqs. 2-3).

A CPE branch is a resistor ``R`` in parallel with a constant-phase element of
coefficient ``C`` (F·s^(α-1)) and order ``α``:  ``I = U/R + C·D^α U``.  With the
short-memory G-L derivative of length ``L`` (Zeng Eq. 2),

    h^-α Σ_{j=0..L} w_j U_{k-j} = -U_k/(R C) + I_k / C,   w_j = (-1)^j binom(α, j)

Zeng Eq. 3 evaluates the right-hand side at ``k-1`` (explicit).  That form is only
stable while ``h^α < 2 R C``; real recordings log rests every 60-300 s, so here the
right-hand side is taken at ``k`` (implicit, unconditionally stable):

    U_k = (g I_k - Σ_{j=1..L} w_j U_{k-j}) / (1 + g/R),   g = h^α / C.

For α = 1 this is the backward-Euler integer-order RC branch.  ``h`` is the actual
interval before the sample (DESIGN §3).  With non-uniform steps the G-L weights
assume an equally spaced history: an approximation, stated here once.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter


def gl_weights(alpha: np.ndarray | float, memory_length: int) -> np.ndarray:
    """G-L weights ``w_j = (-1)^j binom(α, j)`` for ``j = 0..L`` (Zeng Eq. 2).

    Uses the recursion ``w_0 = 1, w_j = w_{j-1} (1 - (α+1)/j)``; works on any shape
    of ``alpha`` and returns ``alpha.shape + (L+1,)``.
    """
    alpha = np.asarray(alpha, dtype=float)
    j = np.arange(1, memory_length + 1, dtype=float)
    factors = 1.0 - (alpha[..., None] + 1.0) / j
    w = np.empty(alpha.shape + (memory_length + 1,))
    w[..., 0] = 1.0
    w[..., 1:] = np.cumprod(factors, axis=-1)
    return w


def cpe_gain(dt_s: np.ndarray | float, c: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``g = h^α / C`` of the implicit G-L step."""
    return np.power(np.maximum(dt_s, 1e-9), alpha) / c


def cpe_step(
    history: np.ndarray,
    current_a: np.ndarray,
    dt_s: np.ndarray | float,
    r: np.ndarray,
    c: np.ndarray,
    alpha: np.ndarray,
    weights: np.ndarray,
) -> np.ndarray:
    """Advance CPE branch voltages one step (implicit G-L, see module docstring).

    ``history[..., j-1]`` holds ``U_{k-j}`` (newest first, ``L`` entries);
    ``weights`` is :func:`gl_weights` output (``L+1`` entries).  Shapes broadcast:
    ``r, c, alpha`` like ``history[..., 0]``; ``current_a`` against them.
    """
    g = cpe_gain(dt_s, c, alpha)
    memory = np.einsum("...j,...j->...", weights[..., 1:], history)
    return (g * current_a - memory) / (1.0 + g / r)


def push_history(history: np.ndarray, newest: np.ndarray) -> None:
    """Shift ``history`` one step older in place and store ``newest`` at index 0."""
    history[..., 1:] = history[..., :-1]
    history[..., 0] = newest


def cpe_trajectory(
    current_a: np.ndarray,
    dt_s: np.ndarray,
    r: np.ndarray,
    c: np.ndarray,
    alpha: np.ndarray,
    weights: np.ndarray,
    history: np.ndarray,
    min_filter_run: int = 32,
) -> np.ndarray:
    """Branch voltages ``U[T, N, B]`` of :func:`cpe_step` applied along a recording.

    ``current_a[T, N]`` and ``dt_s[T]`` are the samples; ``r, c`` are ``[N, B]`` or, when
    they change with the sample (SOC-dependent resistances), ``[T, N, B]``; ``alpha[N, B]``
    and ``weights[N, B, L+1]`` as for :func:`cpe_step`.  ``history[N, B, L]`` (newest first)
    is the state before the first sample and is left at the state after the last.

    Over a run of equal steps with fixed ``R, C`` the implicit G-L step is the linear
    recursion ``(1 + g/R) U_k + Σ_{j=1..L} w_j U_{k-j} = g I_k`` with constant
    coefficients, an IIR filter (:func:`scipy.signal.lfilter`, started from the last ``L``
    voltages).  Shorter runs, and steps whose ``R, C``
    change, are taken one sample at a time.
    """
    steps = current_a.shape[0]
    length = history.shape[-1]
    # buf[length + k] = U_k; buf[:length] = the history, oldest first
    buf = np.empty((length + steps,) + history.shape[:-1])
    buf[:length] = np.moveaxis(history[..., ::-1], -1, 0)
    w_oldest_first = np.moveaxis(weights[..., :0:-1], -1, 0)  # w_L .. w_1, [L, N, B]
    g = cpe_gain(np.asarray(dt_s, dtype=float)[:, None, None], c, alpha)
    numerator = g * current_a[:, :, None]
    denominator = 1.0 + g / r
    fixed = np.ndim(r) == 2 and np.ndim(c) == 2
    for k0, k1 in _equal_step_runs(dt_s):
        if fixed and k1 - k0 >= min_filter_run:
            _filter_run(buf, k0, k1, g[k0], denominator[k0], weights, current_a)
            continue
        for k in range(k0, k1):
            memory = np.einsum("lnb,lnb->nb", buf[k:k + length], w_oldest_first)
            buf[length + k] = (numerator[k] - memory) / denominator[k]
    history[...] = np.moveaxis(buf[steps:][::-1], 0, -1)
    return buf[length:]


def _equal_step_runs(dt_s: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` of the runs of equal consecutive steps."""
    dt = np.asarray(dt_s, dtype=float)
    cuts = (np.flatnonzero(dt[1:] != dt[:-1]) + 1).tolist()
    return list(zip([0] + cuts, cuts + [dt.size]))


def _filter_run(buf: np.ndarray, k0: int, k1: int, g: np.ndarray, denominator: np.ndarray,
                weights: np.ndarray, current_a: np.ndarray) -> None:
    """Fill ``buf`` over samples ``k0..k1`` (one step size, fixed ``R, C``) branch by branch
    with the constant-coefficient recursion of :func:`cpe_trajectory`."""
    length = weights.shape[-1] - 1
    a_coef = np.concatenate((denominator[..., None], weights[..., 1:]), axis=-1)  # [N, B, L+1]
    past = np.moveaxis(buf[k0:k0 + length][::-1], 0, -1)  # U_{k0-1}, U_{k0-2}, ... [N, B, L]
    # lfilter's start state for these past outputs (what scipy.signal.lfiltic computes),
    # for every branch at once: zi_m = -Σ_{q=1..L-m} a_{m+q} U_{k0-q} / a_0
    zi = np.empty(past.shape)
    for m in range(length):
        zi[..., m] = -np.einsum("nbq,nbq->nb", a_coef[..., m + 1:], past[..., :length - m]) / denominator
    for n, b in np.ndindex(*g.shape):
        buf[length + k0:length + k1, n, b] = lfilter(g[n, b:b + 1], a_coef[n, b], current_a[k0:k1, n],
                                                     zi=zi[n, b])[0]
