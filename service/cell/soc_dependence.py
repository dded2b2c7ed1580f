"""SOC dependence of the resistances: ``R_ohm(SOC, T)`` and ``R_ct, R_df (SOC, T)`` as scale tables.

The MTS-FOM of Zeng (Eqs. 2-3, 6) has one set of parameters per temperature.  A real
cell's resistances are not flat in SOC: on the Panasonic 18650PF the 10 s pulse
resistance of the HPPC test at 0 °C is 133 mΩ at full charge, 70-78 mΩ between 30 and
70 % SOC and 136 mΩ near empty (``socd fit --soc-resistance`` prints the table it
measured).  Lookup tables over SOC and temperature are how equivalent-circuit models are
usually parameterised (the Simscape battery blocks, most BMS models); here they are
*scales* on top of the per-temperature parameters, so the fitted parameters, the online
identifiers (which correct the scaled nominal multiplicatively) and every other extension
keep their meaning:

    R_ohm(SOC, T) = R_ohm(T) · g_ohm(SOC, T)
    R_b(SOC, T)   = R_b(T) · g_pol(SOC, T),   C_b(SOC, T) = C_b(T) / g_pol(SOC, T)   (b = ct, df)

The CPE branches keep their time constant ``(R_b C_b)^(1/α_b)``: the HPPC pulse measures
the size of the polarisation, not how its time scale moves with SOC.  The scales are read
at the SOC of the previous sample (the model is explicit in the parameters).  Outside the
measured SOC range the end values hold; between temperatures the scales are linear in T,
outside the table's temperatures the nearest row holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.cell.ocv import grid_lookup, temperature_rows

GRID_POINTS = 101


@dataclass(frozen=True)
class SocScaleTable:
    """``g_ohm[k, s]`` and ``g_pol[k, s]`` at ``temps_c[k]`` and a uniform SOC grid on [0, 1]."""

    temps_c: np.ndarray
    g_ohm: np.ndarray
    g_pol: np.ndarray

    @classmethod
    def from_points(cls, soc: list[float], temps_c: list[float], r_ohm_scale: list[list[float]],
                    r_pol_scale: list[list[float]]) -> SocScaleTable:
        soc_a = np.asarray(soc, dtype=float)
        temps = np.asarray(temps_c, dtype=float)
        order = np.argsort(temps)
        grid = np.linspace(0.0, 1.0, GRID_POINTS)
        # np.interp holds the end values outside the measured SOC range
        g_ohm = np.array([np.interp(grid, soc_a, np.asarray(r_ohm_scale[k], float)) for k in order])
        g_pol = np.array([np.interp(grid, soc_a, np.asarray(r_pol_scale[k], float)) for k in order])
        return cls(temps_c=temps[order], g_ohm=g_ohm, g_pol=g_pol)

    def __call__(self, soc: np.ndarray, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(g_ohm, g_pol)`` for each cell at its SOC and temperature (arrays broadcast)."""
        soc, temp_c = np.broadcast_arrays(np.asarray(soc, float), np.asarray(temp_c, float))
        soc = np.nan_to_num(soc, nan=0.5)
        k0, k1, f = temperature_rows(self.temps_c, np.nan_to_num(temp_c, nan=float(self.temps_c[0])))
        return grid_lookup(self.g_ohm, k0, k1, f, soc), grid_lookup(self.g_pol, k0, k1, f, soc)


def scaled_resistances(r_ohm: np.ndarray, r: np.ndarray, c: np.ndarray, g_ohm: np.ndarray,
                       g_pol: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(R_ohm·g_ohm, R·g_pol, C/g_pol)`` with ``g_pol`` on the two base branches (charge
    transfer, diffusion) only; extra branches from extensions keep their values.
    ``r_ohm``: ``[N]``; ``r, c``: ``[N, B]``; ``g_*``: ``[N]``, or ``[T, N]`` for a
    recording's samples (the result is then ``[T, N]`` and ``[T, N, B]``)."""
    g = np.ones(np.shape(g_pol) + r.shape[-1:])
    g[..., :2] = g_pol[..., None]
    return r_ohm * g_ohm, r * g, c / g


def pulse_resistances(time_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray, soc: np.ndarray,
                      capacity_ah: float, rest_a: float, pulse_s: float = 10.0, min_rest_s: float = 300.0,
                      max_c_rate: float = 2.0, ocv_v: np.ndarray | None = None) -> np.ndarray:
    """Discharge pulses from rest in an HPPC-like recording: ``[[soc, R0, R_pol], ...]``.

    ``R0 = ΔV/ΔI`` over the first sample of the pulse (the ohmic jump) and ``R_pol`` the
    further drop at ``pulse_s`` per ampere; with ``ocv_v`` (the OCV at each sample's SOC) the
    OCV's own fall during the pulse is taken out of it (near empty, where the OCV is steep,
    it is a large part of the drop).  A pulse counts when the cell rested
    (|I| < ``rest_a``) for ``min_rest_s`` before it, its current stays within 5 % of its
    first sample for ``pulse_s`` and its C-rate is at most ``max_c_rate`` (higher pulses
    carry the Butler–Volmer curvature, a current dependence rather than an SOC one).  The
    sample step at the onset must be at most 1.5 s so the ohmic jump is not smeared.
    """
    out = []
    n = time_s.size
    rest = np.abs(current_a) < rest_a
    # start of the rest that ends at each index: the time of the latest sample under load
    last_load = np.maximum.accumulate(np.where(rest, 0, np.arange(n)))
    rest_start = time_s[last_load]
    for k in range(1, n):
        i_k = current_a[k]
        if not (rest[k - 1] and i_k > rest_a * 10 and i_k <= max_c_rate * capacity_ah):
            continue
        if time_s[k] - time_s[k - 1] > 1.5 or time_s[k - 1] - rest_start[k - 1] < min_rest_s:
            continue
        end = int(np.searchsorted(time_s, time_s[k] + pulse_s - 1.0 - 1e-6))
        if end >= n or time_s[end] - time_s[k] > pulse_s + 0.5:
            continue
        window = current_a[k:end + 1]
        if np.any(np.abs(window - i_k) > 0.05 * i_k):
            continue
        d_i = i_k - current_a[k - 1]
        r0 = (voltage_v[k - 1] - voltage_v[k]) / d_i
        drop = voltage_v[k - 1] - voltage_v[end]
        if ocv_v is not None:
            drop -= ocv_v[k - 1] - ocv_v[end]
        r10 = drop / d_i
        if r0 > 0 and r10 > r0:
            out.append((float(soc[k - 1]), float(r0), float(r10 - r0)))
    return np.array(out).reshape(-1, 3)


def scale_rows(pulses: np.ndarray, soc_bin: float = 0.025, min_levels: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Pulses → ``(soc_levels, g_ohm, g_pol)``: the median R0 and R_pol per SOC level
    (pulses within ``soc_bin``), each divided by its median over the levels.  ``None`` when
    fewer than ``min_levels`` SOC levels carry a pulse (too little to draw a curve)."""
    if pulses.shape[0] == 0:
        return None
    order = np.argsort(pulses[:, 0])
    p = pulses[order]
    levels: list[list[np.ndarray]] = []
    for row in p:
        if levels and row[0] - levels[-1][0][0] <= soc_bin:
            levels[-1].append(row)
        else:
            levels.append([row])
    if len(levels) < min_levels:
        return None
    soc = np.array([np.median([r[0] for r in lv]) for lv in levels])
    r0 = np.array([np.median([r[1] for r in lv]) for lv in levels])
    rp = np.array([np.median([r[2] for r in lv]) for lv in levels])
    return soc, r0 / np.median(r0), rp / np.median(rp)
