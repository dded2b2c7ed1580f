"""One-state hysteresis (Zeng Eq. 1), in this project's sign convention.

    U_h,k = A U_h,k-1 + (1 - A)·(-sgn I_k)·U_H,   A = exp(-|ε η I_k h| / (3600 Q))

Current is positive on discharge (DESIGN §3), so ``-sgn(I)`` drives ``U_h`` to
``+U_H`` on charge and ``-U_H`` on discharge.  Zeng's Eq. 1 omits the step ``h``
and the 3600 s/h factor; both are restored here so ``ε`` is dimensionless
(the number of capacity-throughputs per e-fold, inverted).
"""

from __future__ import annotations

import numpy as np

from service.cell.units import SECONDS_PER_HOUR


def hysteresis_decay(
    current_a: np.ndarray, dt_s: np.ndarray | float, rate: np.ndarray, capacity_ah: np.ndarray
) -> np.ndarray:
    """``A_h`` of Zeng Eq. 1 with the step and unit factors restored."""
    return np.exp(-np.abs(rate * current_a * dt_s) / (SECONDS_PER_HOUR * capacity_ah))


def hysteresis_coefficients(
    current_a: np.ndarray, dt_s: np.ndarray | float, u_h_max: np.ndarray, rate: np.ndarray, capacity_ah: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)`` of Zeng Eq. 1 as ``U_h,k = A U_h,k-1 + B``: the decay and what the current drives."""
    a = hysteresis_decay(current_a, dt_s, rate, capacity_ah)
    return a, (1.0 - a) * (-np.sign(current_a)) * u_h_max


def hysteresis_step(
    u_h: np.ndarray,
    current_a: np.ndarray,
    dt_s: np.ndarray | float,
    u_h_max: np.ndarray,
    rate: np.ndarray,
    capacity_ah: np.ndarray,
) -> np.ndarray:
    """Next hysteresis voltage (Zeng Eq. 1, sign-corrected)."""
    a, b = hysteresis_coefficients(current_a, dt_s, u_h_max, rate, capacity_ah)
    return a * u_h + b
