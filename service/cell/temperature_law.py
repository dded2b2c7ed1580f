"""How the resistances move with temperature inside one fitted point's recordings (Arrhenius).

A drive cycle in the cold warms the cell by 10-20 K, and its resistances fall by half or more
on the way.  ``socd fit`` fits each temperature group's point with this law along the recorded
temperature (:func:`service.cell.fitting.fit_parameters`, ``temperature_law``), so the point is
the parameters at the group's mean temperature rather than one compromise over the span; the
profile is then read between its points as before (:meth:`CellProfile.parameters_at`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from service.cell.profile import GAS_CONSTANT, KELVIN, CellParameters


def temperature_law_factor(ea_j_mol: float | np.ndarray, temp_c: np.ndarray | float,
                           point_temp_c: float) -> np.ndarray:
    """``exp(Ea/R (1/T - 1/T_point))``: a resistance at ``temp_c`` over its value at the point."""
    inv = 1.0 / (np.asarray(temp_c, dtype=float) + KELVIN) - 1.0 / (point_temp_c + KELVIN)
    return np.exp(np.asarray(ea_j_mol, dtype=float) / GAS_CONSTANT * inv)


def scaled_by_law(p: CellParameters, factor: np.ndarray) -> CellParameters:
    """``R_ohm``, ``R_ct``, ``R_df`` times ``factor`` (per cell or candidate), the Butler-Volmer
    exchange current divided by it (i0 ∝ 1/R_ct), the CPE coefficients kept, so the time
    constants grow with the resistances, as charge transfer and solid diffusion slow in the cold."""
    r = np.array(p.r, copy=True)
    r[..., :2] = r[..., :2] * factor[..., None]
    return dataclasses.replace(p, r_ohm=p.r_ohm * factor, r=r, kinetics_i0_a=p.kinetics_i0_a / factor)
