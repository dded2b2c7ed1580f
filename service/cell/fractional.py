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


def resized_history(history: np.ndarray, length: int) -> np.ndarray:
    """A newest-first memory ``[..., L]`` cut or zero-padded (relaxed) to ``length`` entries."""
    out = np.zeros(history.shape[:-1] + (length,))
    keep = min(length, history.shape[-1])
    out[..., :keep] = history[..., :keep]
    return out


def push_history(history: np.ndarray, newest: np.ndarray) -> None:
    """Shift ``history`` one step older in place and store ``newest`` at index 0."""
    history[..., 1:] = history[..., :-1]
    history[..., 0] = newest
