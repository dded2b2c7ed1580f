"""Features of a recording's current that both the candidate effects (:mod:`.effects`) and the
signatures (:mod:`.signatures`) regress the residual on: a first-order low-pass and the
Eq.-1 hysteresis direction state.  Here, below both, so neither imports the other for them."""

from __future__ import annotations

import numpy as np

from service.cell.hysteresis import hysteresis_decay


def lowpass(x: np.ndarray, t: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order low-pass of ``x`` with time constant ``tau_s`` on a non-uniform grid."""
    y = np.empty_like(x)
    acc = 0.0
    dt = np.diff(t, prepend=t[0])
    a = np.exp(-dt / tau_s)
    for k in range(x.size):
        acc = a[k] * acc + (1.0 - a[k]) * x[k]
        y[k] = acc
    return y


def direction_state(time_s: np.ndarray, current_a: np.ndarray, capacity_ah: float, rate: float) -> np.ndarray:
    """The Eq.-1 hysteresis state with ``U_H = 1`` (+1 after charge, −1 after discharge) from 0,
    the branch of a cell whose history is unknown (:func:`service.cell.hysteresis.hysteresis_step`)."""
    dt = np.diff(time_s, prepend=time_s[0])
    decay = hysteresis_decay(current_a, dt, rate, capacity_ah)
    target = -np.sign(current_a)
    out = np.empty(time_s.size)
    h = 0.0
    for k in range(time_s.size):
        h = decay[k] * h + (1.0 - decay[k]) * target[k]
        out[k] = h
    return out
