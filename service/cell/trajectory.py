"""The MTS-FOM along a whole recording, for ``N`` cells or parameter candidates at once.

:class:`service.cell.model.MtsFom` advances one sample at a time, as the online
estimators need.  Along a recorded current most of the model is known before the CPE
branch voltages are, so here each part is computed for the whole recording at once:

* the SOC (Zeng Eq. 4) is a running difference, and the SOC-dependent resistance scales
  follow from it;
* the hysteresis voltage (Zeng Eq. 1) and the solid-diffusion surface lag are first-order
  recursions whose coefficients are known in advance;
* the CPE branches (Zeng Eqs. 2-3, implicit) are a linear recursion in their own last
  ``L`` values, one banded linear system per branch (:func:`cpe_trajectory`);
* the OCV, Zeng Eq. 6 and the Butler-Volmer term have no state.

The parts are the functions ``MtsFom.step`` calls, applied in the same order, with the
parameters re-read when the temperature moves (the rule of :func:`drive`).  Equality with
stepping :class:`MtsFom` is checked in the tests.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg.lapack import dtbtrs

from service.cell.fractional import cpe_gain, cpe_step, push_history
from service.cell.hysteresis import hysteresis_coefficients
from service.cell.model import (
    DEFAULT_MEMORY_LENGTH,
    TEMP_FOLLOW_K,
    MtsFom,
    kinetic_overpotential,
    parameter_updates,
    surface_deficit_coefficients,
    terminal_voltage,
)
from service.cell.profile import CellParameters, CellProfile
from service.cell.soc_dependence import scaled_resistances
from service.cell.units import SECONDS_PER_HOUR


def first_order_trajectory(decay: np.ndarray, drive: np.ndarray, start: np.ndarray) -> np.ndarray:
    """``y_k = decay_k · y_{k-1} + drive_k`` from ``y_{-1} = start``, for ``[T, N]`` inputs."""
    out = np.empty_like(drive)
    y = start
    for k in range(drive.shape[0]):
        y = decay[k] * y + drive[k]
        out[k] = y
    return out


def simulate_batch(
    profile: CellProfile,
    time_s: np.ndarray,
    current_a: np.ndarray,
    temp_c: np.ndarray,
    soc0: np.ndarray,
    params: CellParameters,
    memory_length: int = DEFAULT_MEMORY_LENGTH,
    u_h0: np.ndarray | float = 0.0,
    params_at: Callable[[float], CellParameters] | None = None,
    temp_update_k: float = TEMP_FOLLOW_K,
    surface: tuple[np.ndarray, np.ndarray] | None = None,
    u_h0_branch: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Terminal voltage and SOC ``[T, N]`` of ``N`` candidates along one recording.

    ``params_at(T)`` (optional) gives the candidates' parameters at temperature ``T``;
    they are re-read when the temperature moves by more than ``temp_update_k``.
    ``surface = (tau_s[N], gain[N])`` (optional) sets the candidates' solid-diffusion
    surface lag (otherwise the profile's ``extensions.diffusion_surface``, if any).
    ``u_h0_branch`` adds that many of each candidate's ``U_H`` to ``u_h0`` (see
    :class:`service.cell.fitting.FitSegment`).
    """
    n = params.r.shape[0]
    soc0 = np.broadcast_to(np.asarray(soc0, dtype=float), (n,))
    temp_c = np.asarray(temp_c, dtype=float)
    p = params_at(float(temp_c[0])) if params_at is not None else params
    u_h_start = np.broadcast_to(u_h0, (n,)) + u_h0_branch * p.u_h_max
    model = MtsFom(profile, p, soc0, memory_length, u_h_start)
    if surface is not None:
        model.surface_tau_s = np.broadcast_to(np.asarray(surface[0], dtype=float), (n,)).copy()
        model.surface_gain = np.broadcast_to(np.asarray(surface[1], dtype=float), (n,)).copy()
    dt = np.diff(time_s, prepend=time_s[0])
    size = time_s.size
    starts = parameter_updates(temp_c, temp_update_k) if params_at is not None else [0]
    parts: list[tuple[np.ndarray, ...]] = []
    hyst = bool(np.any(p.u_h_max != 0)) or bool(np.any(model.u_h != 0))
    with np.errstate(all="ignore"):
        for k0, k1 in zip(starts, starts[1:] + [size]):
            if k0 > 0:
                model.set_params(params_at(float(temp_c[k0])))
            parts.append(_advance(model, dt[k0:k1], current_a[k0:k1], temp_c[k0:k1], hyst))
        soc, u_h, x_surf, ohm_v, branch_v, kinetic_v = (np.concatenate(a, axis=0) for a in zip(*parts))
        p = model.params
        temp_tn = np.broadcast_to(temp_c[:, None], soc.shape)
        ocv = model.open_circuit(temp_tn, soc if model.surface_tau_s is None else soc - x_surf)
        v = terminal_voltage(ocv, model.hysteresis_voltage(u_h, p.u_h_max), 1.0, ohm_v, branch_v)
    return v - kinetic_v, soc


def _advance(model: MtsFom, dt: np.ndarray, current_a: np.ndarray, temp_c: np.ndarray,
             hyst: bool) -> tuple[np.ndarray, ...]:
    """Advance ``model`` over samples with fixed parameters; return ``[T, N]`` arrays of
    SOC, ``U_h``, surface deficit, ohmic drop, branch-voltage sum and Butler-Volmer term (with
    these parameters: its linear part is in this stretch's ``R_ohm``), and leave ``model`` in its
    end state (as ``MtsFom.step`` would)."""
    p = model.params
    h = dt[:, None]
    i = current_a[:, None] - p.current_bias_a
    soc_start = model.soc
    # Zeng Eq. 4 (service.cell.model.soc_step), the same operations in the same order
    charge = i * h / (SECONDS_PER_HOUR * p.capacity_ah)
    soc = np.subtract.accumulate(np.vstack([soc_start[None], charge]))[1:]
    r_ohm, r, c = p.r_ohm, p.r, p.c
    if model.soc_scale is not None:  # resistances at the SOC before each step, as MtsFom.step
        soc_before = np.vstack([soc_start[None], soc[:-1]])
        g_ohm, g_pol = model.soc_scale(soc_before, np.broadcast_to(temp_c[:, None], soc.shape))
        r_ohm, r, c = scaled_resistances(p.r_ohm, p.r, p.c, g_ohm, g_pol)
    x_surf = np.zeros_like(soc)
    if model.surface_tau_s is not None:
        a, b = surface_deficit_coefficients(i, h, model.surface_tau_s, model.surface_gain, p.capacity_ah)
        x_surf = first_order_trajectory(a, b, model.x_surf)
        model.x_surf = x_surf[-1]
    u_h = np.broadcast_to(model.u_h, soc.shape)
    if hyst:
        a, b = hysteresis_coefficients(i, h, p.u_h_max, p.hyst_rate, p.capacity_ah)
        u_h = first_order_trajectory(a, b, model.u_h)
        model.u_h = u_h[-1]
    branch = cpe_trajectory(i, dt, r, c, p.alpha, model.weights, model.history)
    model.soc = soc[-1]
    kinetic_v = np.zeros_like(soc)
    if np.any(np.isfinite(p.kinetics_i0_a)):
        kinetic_v = kinetic_overpotential(i, p.kinetics_i0_a[None, :], np.broadcast_to(temp_c[:, None], soc.shape))
    return soc, u_h, x_surf, r_ohm * i, branch.sum(axis=-1), kinetic_v


def simulate(
    profile: CellProfile,
    time_s: np.ndarray,
    current_a: np.ndarray,
    temp_c: np.ndarray,
    soc0: float | np.ndarray,
    params: CellParameters | None = None,
    memory_length: int = DEFAULT_MEMORY_LENGTH,
    u_h0: float | np.ndarray = 0.0,
    temperature_dependent: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulate terminal voltage and SOC along a recording.

    With ``params`` given (``N`` candidates), they are used as they are at every
    step and the result is ``[T, N]``; otherwise the profile's parameters follow the
    recorded temperature (``temperature_dependent``) and the result is ``[T]``.
    """
    single = params is None
    if single:
        params = profile.parameters_at(float(temp_c[0]), n_cells=1)
    n = params.r.shape[0]
    follow = single and ((temperature_dependent and len(profile.parameters) > 1)
                         or profile.extensions.arrhenius is not None)
    v, soc = simulate_batch(
        profile, time_s, current_a, temp_c, np.broadcast_to(soc0, (n,)), params, memory_length,
        np.broadcast_to(u_h0, (n,)),
        params_at=(lambda t: profile.parameters_at(t, n_cells=1)) if follow else None,
    )
    if single:
        return v[:, 0], soc[:, 0]
    return v, soc


def cpe_trajectory(
    current_a: np.ndarray,
    dt_s: np.ndarray,
    r: np.ndarray,
    c: np.ndarray,
    alpha: np.ndarray,
    weights: np.ndarray,
    history: np.ndarray,
    min_banded_steps: int = 64,
) -> np.ndarray:
    """Branch voltages ``U[T, N, B]`` of :func:`cpe_step` applied along a recording.

    ``current_a[T, N]`` and ``dt_s[T]`` are the samples; ``r, c`` are ``[N, B]`` or, when
    they change with the sample (SOC-dependent resistances), ``[T, N, B]``; ``alpha[N, B]``
    and ``weights[N, B, L+1]`` as for :func:`cpe_step`.  ``history[N, B, L]`` (newest first)
    is the state before the first sample and is left at the state after the last.

    Along the recording the implicit G-L steps of one branch are one linear system,
    ``(1 + g_k/R_k) U_k + Σ_{j=1..L} w_j U_{k-j} = g_k I_k``: lower triangular with ``L``
    sub-diagonals, the history's part moved to the right-hand side.  It is solved by
    forward substitution in LAPACK (``dtbtrs``), branch by branch; a few samples are
    stepped with :func:`cpe_step`.
    """
    steps, length = current_a.shape[0], history.shape[-1]
    if steps < min_banded_steps:
        out = np.empty(current_a.shape + history.shape[1:2])
        per_sample = np.ndim(r) == 3
        for k in range(steps):
            r_k, c_k = (r[k], c[k]) if per_sample else (r, c)
            out[k] = cpe_step(history, current_a[k][:, None], dt_s[k], r_k, c_k, alpha, weights)
            push_history(history, out[k])
        return out
    g = cpe_gain(np.asarray(dt_s, dtype=float)[:, None, None], c, alpha)
    rhs = g * current_a[:, :, None]
    diagonal = np.broadcast_to(1.0 + g / r, rhs.shape)
    for k in range(min(length, steps)):  # U_{k-j} before the first sample: the history
        rhs[k] -= np.einsum("nbj,nbj->nb", weights[..., k + 1:], history[..., :length - k])
    out = _solve_lower_banded(diagonal, weights, rhs)
    newest_first = np.concatenate([np.moveaxis(out[::-1], 0, -1), history], axis=-1)
    history[...] = newest_first[..., :length]
    return out


def _solve_lower_banded(diagonal: np.ndarray, weights: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``U[T, N, B]`` of the banded systems of :func:`cpe_trajectory`, one per branch."""
    length = weights.shape[-1] - 1
    out = np.empty_like(rhs)
    band = np.empty((length + 1, rhs.shape[0]))  # LAPACK's band storage: band[i, k] = A[k+i, k]
    for n, b in np.ndindex(*rhs.shape[1:]):
        band[0] = diagonal[:, n, b]
        band[1:] = weights[n, b, 1:, None]
        u, info = dtbtrs(band, rhs[:, n, b:b + 1], uplo="L")
        out[:, n, b] = u[:, 0] if info == 0 else np.nan
    return out
