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
  degrees when the ambient moves; the voltage never enters.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

#: RMS misfit of the constant-ambient thermal model above which the ambient is taken to move
AMBIENT_DRIFT_K = 0.5


def _thermal_sim(th: np.ndarray, time_s: np.ndarray, load: np.ndarray, t0: float) -> np.ndarray:
    t_amb, ln_a, ln_tau = th
    a, tau = math.exp(ln_a), math.exp(ln_tau)
    dt = np.diff(time_s, prepend=time_s[0])
    alpha = np.exp(-dt / tau)
    out = np.empty_like(time_s)
    x = t0
    drive = t_amb + a * load
    for k in range(time_s.size):
        x = alpha[k] * x + (1.0 - alpha[k]) * drive[k]
        out[k] = x
    return out


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


def signatures(time_s: np.ndarray, current_a: np.ndarray, temperature_c: np.ndarray, capacity_ah: float) -> dict:
    """``{effect: {"nominated": bool, "statistic": float, ...}}`` for the effects that have one."""
    amb = ambient_drift_k(time_s, current_a, temperature_c, capacity_ah)
    return {
        "temperature": {"nominated": bool(amb["rms_k"] >= AMBIENT_DRIFT_K), "statistic": round(amb["rms_k"], 3),
                        "what": "RMS misfit (K) of a constant-ambient self-heating model to the temperature",
                        "threshold": AMBIENT_DRIFT_K, **{k: round(v, 3) for k, v in amb.items()}},
    }
