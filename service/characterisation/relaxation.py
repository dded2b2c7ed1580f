"""Slow relaxation: a long time constant measured from the voltage recovery in long rests.

After a load, a Li-ion cell's rest voltage keeps creeping towards the OCV for an hour or
more (solid diffusion evening out the particles).  The model's two CPE branches cannot
hold that: the G-L short memory (Zeng Eq. 2, ``L`` samples) forgets a fractional
branch's tail after a few samples, so a fit to a drive cycle gives the diffusion branch
a time constant of seconds to a minute.  Under a long drive the missing slow
polarisation is an almost constant offset, and an OCV curve fitted jointly with the
model (``socd fit`` without an OCV test) takes it into the OCV: the curve then sits low
by that offset, and an estimator reads the cell's fully relaxed voltage in a later long
rest as a higher SOC (docs/results/cell_options.md, CALCE INR18650-20R).

The measurement is the classic relaxation analysis.  In a rest of at least
:data:`LONG_REST_S`, from :data:`SETTLE_S` after its start (the fast branches, with time
constants up to a minute, have died out), the voltage is ``V(t) = V_∞ − U_s(t)`` with
``U_s`` an RC branch (``R_s, τ_s``) driven by the recording's whole current history,
and ``V_∞`` a free level per rest (the OCV there, whatever the table says).  ``R_s`` and
``τ_s`` are shared by all rests; scipy's least squares fits them, with their standard
errors from the Jacobian.  The branch is added to the profile as an integer-order extra
branch (``extensions.extra_branches``), which the model and the SOC filter carry as one
more state (its parameters stay fixed online).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from service.cell.fitting import small_cell_ratio
from service.cell.profile import BranchSpec
from service.cell.rests import load_level_a
from service.characterisation.ocv_sources import rest_spans
from service.recording import Recording

#: a rest must last this long to carry the slow relaxation
LONG_REST_S = 1800.0
#: rest samples earlier than this after the rest's start are left out (the fast branches)
SETTLE_S = 300.0
#: search range of the slow time constant [s] and resistance [Ω] (the resistance's upper end for a cell
#: of service.cell.fitting.BOUNDS_MIN_CAPACITY_AH or more; raised for a smaller cell by its small_cell_ratio)
TAU_BOUNDS_S = (300.0, 1.0e5)
R_BOUNDS_OHM = (1.0e-5, 1.0)


@dataclass
class SlowRelaxation:
    """The measured slow branch and how well it describes the rests."""

    r_ohm: float
    tau_s: float
    r_std_ohm: float
    tau_std_s: float
    rms_mv: float
    rests: list[str]

    def branch(self) -> BranchSpec:
        return BranchSpec(r=self.r_ohm, c=self.tau_s / self.r_ohm, alpha=1.0)

    def describe(self) -> str:
        return (f"R {1e3 * self.r_ohm:.1f} ± {1e3 * self.r_std_ohm:.1f} mΩ, τ {self.tau_s:.0f} ± {self.tau_std_s:.0f} s "
                f"from {len(self.rests)} rest(s), RMS misfit {self.rms_mv:.2f} mV")


def long_rests(rec: Recording, capacity_ah: float, min_rest_s: float = LONG_REST_S) -> list[tuple[int, int]]:
    """``(first, last)`` sample of every rest of at least ``min_rest_s`` that follows a load."""
    loaded_before = np.maximum.accumulate(np.abs(rec.current_a)) > load_level_a(rec.current_a, capacity_ah)
    return [(k, j) for k, j in rest_spans(rec, capacity_ah, min_rest_s) if k > 0 and loaded_before[k]]


def rc_voltage(time_s: np.ndarray, current_a: np.ndarray, r_ohm: float, tau_s: float) -> np.ndarray:
    """Voltage of an RC branch driven by ``current_a`` (zero-order hold, exact exponential step).

    The recursion ``u_k = d_k u_{k-1} + (1 - d_k) R i_k`` with ``d_k = exp(-Δt_k/τ)`` is
    summed in closed form, ``u_k = e^{-s_k} (d_a u_{a-1} + Σ_{j=a..k} (1 - d_j) R i_j e^{s_j})``
    with ``s = (t - t_a)/τ``, in chunks short enough (``s ≤`` 300) for ``e^s`` to stay finite.
    """
    t = np.asarray(time_s, dtype=float)
    decay = np.exp(-np.diff(t, prepend=t[0]) / tau_s)
    drive = (1.0 - decay) * r_ohm * np.asarray(current_a, dtype=float)
    u = np.empty(t.size)
    prev, a = 0.0, 0
    while a < t.size:
        b = max(int(np.searchsorted(t, t[a] + 300.0 * tau_s, side="right")), a + 1)
        s = (t[a:b] - t[a]) / tau_s
        u[a:b] = np.exp(-s) * (decay[a] * prev + np.cumsum(drive[a:b] * np.exp(s)))
        prev, a = float(u[b - 1]), b
    return u


def measure_slow_relaxation(recordings: list[Recording], capacity_ah: float) -> SlowRelaxation:
    """Fit one slow RC branch to the long rests of ``recordings`` (module docstring).

    Each recording is simulated from its first sample (branch relaxed there), so the charge
    before a full-charge point counts too.  Raises ``ValueError`` naming the recordings when
    none holds a rest of :data:`LONG_REST_S` after a load.
    """
    cases = []  # (recording, sample indices of each of its long rests, past SETTLE_S)
    names = []
    for rec in recordings:
        spans = []
        for a, b in long_rests(rec, capacity_ah):
            idx = np.flatnonzero(rec.time_s[a:b + 1] >= rec.time_s[a] + SETTLE_S) + a
            if idx.size >= 10:
                spans.append(idx)
                names.append(f"{rec.name} {rec.time_s[a]:.0f}-{rec.time_s[b]:.0f} s")
        if spans:
            cases.append((rec, spans))
    if not cases:
        raise ValueError("--slow-branch needs a rest of at least "
                         f"{LONG_REST_S / 60:.0f} min after a load in the recordings; none in "
                         + ", ".join(r.name for r in recordings))
    n_rest = len(names)

    def residuals(th: np.ndarray) -> np.ndarray:
        r, tau = math.exp(th[0]), math.exp(th[1])
        out = []
        levels = iter(th[2:])
        for rec, spans in cases:
            end = spans[-1][-1] + 1  # one simulation per recording, up to its last rest
            u = rc_voltage(rec.time_s[:end], rec.current_a[:end], r, tau)
            out += [rec.voltage_v[idx] - (next(levels) - u[idx]) for idx in spans]
        return np.concatenate(out)

    lo = [math.log(R_BOUNDS_OHM[0]), math.log(TAU_BOUNDS_S[0])] + [0.0] * n_rest
    hi = [math.log(R_BOUNDS_OHM[1] * small_cell_ratio(capacity_ah)), math.log(TAU_BOUNDS_S[1])] + [10.0] * n_rest
    levels = [float(rec.voltage_v[idx[-1]]) for rec, spans in cases for idx in spans]
    best = None
    for tau0 in (600.0, 3000.0, 15000.0):
        sol = least_squares(residuals, [math.log(0.01), math.log(tau0)] + levels, bounds=(lo, hi), x_scale="jac")
        if best is None or sol.cost < best.cost:
            best = sol
    res = best.fun
    dof = max(res.size - best.x.size, 1)
    s2 = float(res @ res) / dof
    try:
        cov = np.linalg.pinv(best.jac.T @ best.jac) * s2
        sd = np.sqrt(np.clip(np.diag(cov)[:2], 0.0, None))
    except np.linalg.LinAlgError:
        sd = np.array([np.inf, np.inf])
    r, tau = math.exp(best.x[0]), math.exp(best.x[1])
    return SlowRelaxation(r_ohm=r, tau_s=tau, r_std_ohm=r * float(sd[0]), tau_std_s=tau * float(sd[1]),
                          rms_mv=1e3 * math.sqrt(float(np.mean(res**2))), rests=names)
