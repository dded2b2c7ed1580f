"""The multi-time-scale fractional-order cell model (Zeng Eqs. 1-6), whole pack at once.

State per cell: CPE branch voltages (branch 0 = charge transfer ``U_cd``, branch 1 =
diffusion ``U_df``, further branches from extensions) with their G-L memory, ``SOC``
and hysteresis ``U_h`` (Zeng Eq. 5).  Terminal voltage (Zeng Eq. 6, current positive
= discharge):

    U_L = OCV(SOC - x, T) + U_h - R_ohm I - Σ_b U_b - η_kin(I)

``η_kin`` is zero unless the Butler–Volmer extension is set; ``x`` (bulk − surface SOC,
:class:`service.cell.profile.SurfaceDiffusionSpec`) is zero unless the solid-diffusion
surface extension is set; the resistances follow SOC when the profile carries
resistance scales (:mod:`service.cell.soc_dependence`).  SOC follows Zeng Eq. 4
with the sample period and 3600 s/h restored: ``SOC_k = SOC_{k-1} - I_k h / (3600 Q)``
(backward zero-order hold: the current of sample k flowed over (t_{k-1}, t_k]).
"""

from __future__ import annotations

import numpy as np

from service.cell.fractional import cpe_step, gl_weights, push_history
from service.cell.hysteresis import hysteresis_step
from service.cell.ocv import OcvTable
from service.cell.profile import CellParameters, CellProfile, kinetic_voltage_v
from service.cell.soc_dependence import scaled_resistances
from service.cell.units import SECONDS_PER_HOUR

DEFAULT_MEMORY_LENGTH = 16
#: the temperature move (K) after which a simulation re-reads the parameters along a recording
TEMP_FOLLOW_K = 0.2


def soc_step(soc: np.ndarray, current_a: np.ndarray, dt_s, capacity_ah: np.ndarray) -> np.ndarray:
    """Coulomb counting step (Zeng Eq. 4, with h and 3600 s/h; discharge positive)."""
    return soc - current_a * dt_s / (SECONDS_PER_HOUR * capacity_ah)


def parameter_updates(temp_c: np.ndarray, update_k: float = TEMP_FOLLOW_K) -> list[int]:
    """Sample indices at which a simulation reads the parameters: the first sample, and each one
    where the temperature has moved more than ``update_k`` since the last read."""
    starts = [0]
    last = float(temp_c[0])
    for k, t in enumerate(np.asarray(temp_c, dtype=float).tolist()):
        if abs(t - last) > update_k:
            starts.append(k)
            last = t
    return starts


def surface_deficit_coefficients(current_a: np.ndarray, dt_s, tau_s, gain,
                                 capacity_ah) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b)`` of one sample of ``τ dx/dt = gain·I/Q − x`` solved exactly for a current held
    over the sample: ``x_k = a x_{k-1} + b`` (:class:`service.cell.profile.SurfaceDiffusionSpec`)."""
    a = np.exp(-dt_s / tau_s)
    return a, (1.0 - a) * gain * current_a / capacity_ah


def surface_deficit_step(x: np.ndarray, current_a: np.ndarray, dt_s, tau_s, gain, capacity_ah) -> np.ndarray:
    """Bulk − surface SOC after one sample (:func:`surface_deficit_coefficients`)."""
    a, b = surface_deficit_coefficients(current_a, dt_s, tau_s, gain, capacity_ah)
    return a * x + b


def entropic_shift_v(slope_v_per_k: float, ref_temp_c: float, temp_c: np.ndarray) -> np.ndarray:
    """Entropic OCV shift ``dOCV/dT · (T − T_ref)`` of the temperature extension
    (:class:`service.cell.profile.ArrheniusSpec`)."""
    return slope_v_per_k * (np.asarray(temp_c, float) - ref_temp_c)


def kinetic_overpotential(current_a: np.ndarray, i0_a: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
    """Symmetric Butler–Volmer overpotential beyond the linear term: 2RT/F asinh(I/2i0) - linear.

    The linear part is already in ``R_ct``; what remains is the drop in apparent
    resistance at high current.  Zero when ``i0`` is infinite (extension off).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        vt = kinetic_voltage_v(temp_c)
        x = current_a / (2.0 * i0_a)
        eta = vt * (np.arcsinh(x) - x)
    return np.where(np.isfinite(i0_a), eta, 0.0)


def terminal_voltage(
    ocv_v: np.ndarray,
    u_h: np.ndarray,
    r_ohm: np.ndarray,
    current_a: np.ndarray,
    branch_sum_v: np.ndarray,
) -> np.ndarray:
    """Zeng Eq. 6 (current positive = discharge)."""
    return ocv_v + u_h - r_ohm * current_a - branch_sum_v


class MtsFom:
    """Stepwise MTS-FOM for ``N`` cells (or ``N`` parameter candidates) at once."""

    def __init__(
        self,
        profile: CellProfile,
        params: CellParameters,
        soc0: np.ndarray,
        memory_length: int = DEFAULT_MEMORY_LENGTH,
        u_h0: np.ndarray | None = None,
        ocv: OcvTable | None = None,
    ) -> None:
        self.profile = profile
        self.ocv = ocv if ocv is not None else profile.ocv_table()
        self.params = params
        self.memory_length = int(memory_length)
        n, b = params.r.shape
        self.soc = np.array(np.broadcast_to(soc0, (n,)), dtype=float)
        self.u_h = np.zeros(n) if u_h0 is None else np.array(np.broadcast_to(u_h0, (n,)), dtype=float)
        # a one-branch OCV table (HysteresisSpec.table_branch): ocv_table() is already the mean
        # for the profile's U_H; a candidate with another U_H (a fit) moves it by the difference
        self._branch_sign = profile.hysteresis.branch_sign
        self._table_u_h = profile.hysteresis.u_h_max_v
        self.history = np.zeros((n, b, self.memory_length))
        self.weights = gl_weights(params.alpha, self.memory_length)
        entropic = profile.extensions.arrhenius
        self._entropic = 0.0 if entropic is None else entropic.entropic_v_per_k
        self._entropic_ref = 25.0 if entropic is None else entropic.ref_temp_c
        # solid-diffusion surface lag (Extensions.diffusion_surface): None = off
        surf = profile.extensions.diffusion_surface
        self.surface_tau_s: np.ndarray | None = None if surf is None else np.full(n, surf.tau_s)
        self.surface_gain: np.ndarray | None = None if surf is None else np.full(n, surf.gain)
        self.x_surf = np.zeros(n)
        # resistance scales over SOC (Extensions.soc_resistance): None = flat in SOC
        self.soc_scale = profile.soc_scale_table()

    def effective_resistances(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``R_ohm, R, C`` at the present SOC (:mod:`service.cell.soc_dependence`)."""
        p = self.params
        if self.soc_scale is None:
            return p.r_ohm, p.r, p.c
        g_ohm, g_pol = self.soc_scale(self.soc, temp_c)
        return scaled_resistances(p.r_ohm, p.r, p.c, g_ohm, g_pol)

    def surface_step(self, i: np.ndarray, dt_s) -> None:
        """Advance bulk − surface SOC ``x`` (see :class:`SurfaceDiffusionSpec`); no-op when off."""
        if self.surface_tau_s is None:
            return
        self.x_surf = surface_deficit_step(self.x_surf, i, dt_s, self.surface_tau_s, self.surface_gain,
                                           self.params.capacity_ah)

    def set_params(self, params: CellParameters) -> None:
        self.params = params
        self.weights = gl_weights(params.alpha, self.memory_length)

    def open_circuit(self, temp_c: np.ndarray, soc: np.ndarray | None = None) -> np.ndarray:
        v = self.ocv.ocv(self.soc if soc is None else soc, temp_c)
        if self._entropic:
            v = v + entropic_shift_v(self._entropic, self._entropic_ref, temp_c)
        return v

    def hysteresis_voltage(self, u_h: np.ndarray, u_h_max: np.ndarray) -> np.ndarray:
        """``U_h`` as it enters Zeng Eq. 6, plus the branch offset of a candidate whose U_H
        is not the profile's (0 for a mean table, and for every cell of a loaded profile)."""
        if not self._branch_sign:
            return u_h
        return u_h - self._branch_sign * (u_h_max - self._table_u_h)

    def step(self, dt_s: float | np.ndarray, current_a: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Advance every cell by ``dt_s`` under measured ``current_a``; return terminal voltage."""
        p = self.params
        i = current_a - p.current_bias_a
        r_ohm, r, c = self.effective_resistances(temp_c)
        self.soc = soc_step(self.soc, i, dt_s, p.capacity_ah)
        self.surface_step(i, dt_s)
        self.u_h = hysteresis_step(self.u_h, i, dt_s, p.u_h_max, p.hyst_rate, p.capacity_ah)
        u = cpe_step(self.history, i[:, None], dt_s, r, c, p.alpha, self.weights)
        push_history(self.history, u)
        ocv = self.open_circuit(temp_c) if self.surface_tau_s is None else self.open_circuit(temp_c, self.soc - self.x_surf)
        v = terminal_voltage(ocv, self.hysteresis_voltage(self.u_h, p.u_h_max), r_ohm, i, u.sum(axis=-1))
        return v - kinetic_overpotential(i, p.kinetics_i0_a, temp_c)


def drive(
    model: MtsFom,
    time_s: np.ndarray,
    current_a: np.ndarray,
    temp_c: np.ndarray,
    follow_temperature: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Step every cell of ``model`` along one recorded current and temperature; return
    terminal voltage and SOC ``[T, N]``.  With ``follow_temperature`` the profile's
    parameters are re-read whenever the temperature has moved more than ``TEMP_FOLLOW_K``.

    This is the step-by-step reference that :func:`service.cell.trajectory.simulate` computes
    array-wise along a recording."""
    n = model.soc.size
    dt = np.diff(time_s, prepend=time_s[0])
    v = np.empty((time_s.size, n))
    soc = np.empty((time_s.size, n))
    updates = set(parameter_updates(temp_c)[1:]) if follow_temperature else set()
    for k in range(time_s.size):
        tk = np.full(n, temp_c[k])
        if k in updates:
            model.set_params(model.profile.parameters_at(tk))
        v[k] = model.step(dt[k], np.full(n, current_a[k]), tk)
        soc[k] = model.soc
    return v, soc
