"""Run the estimator's cell model along a recording for many parameter candidates.

Fitting an extension needs the model run for ``N`` candidates at once (a Jacobian by
forward differences is ``p + 1`` candidates).  :func:`simulate_candidates` steps
:class:`service.cell.model.MtsFom` -- the estimator's model -- with per-candidate
parameters.  Extensions enter exactly where :mod:`service.cell.model` and
:meth:`CellProfile.parameters_at` put them:

* ``capacity_scale``, ``current_bias_a``, ``kinetics_i0_a``, the hysteresis and extra
  CPE branches are fields of :class:`CellParameters`, per candidate;
* Arrhenius laws rescale ``R_ohm, R_ct, R_df`` when the temperature moves by more than
  0.2 K (the rule of :func:`service.cell.trajectory.simulate`);
* the solid-diffusion surface lag (per candidate ``τ``, gain) is passed to
  :func:`service.cell.trajectory.simulate_batch`, which applies it as :class:`MtsFom` does;
* the entropic term and an OCV correction are additive on the OCV, hence on the
  terminal voltage, and are added to the output.

The reported "after" figures do not come from here: they come from
:func:`service.cell.trajectory.simulate` run on the extended :class:`CellProfile` that
diagnose saves, so what is scored is what ``socd evaluate`` and the service run.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.cell.fitting import FitSegment, decode
from service.cell.ocv import OcvTable
from service.cell.profile import GAS_CONSTANT, KELVIN, CellParameters, CellProfile
from service.cell.trajectory import simulate_batch


@dataclass
class Mods:
    """Per-candidate model parts on top of the base parameters (``N`` candidates)."""

    params: CellParameters
    u_h0: np.ndarray
    ref_temp_c: float
    ea_r_ohm: np.ndarray | None = None
    ea_r_ct: np.ndarray | None = None
    ea_r_df: np.ndarray | None = None
    entropic_v_per_k: np.ndarray | None = None
    ocv_knots_soc: np.ndarray | None = None
    ocv_delta_v: np.ndarray | None = None  # [N, K]
    surface_tau_s: np.ndarray | None = None  # solid-diffusion surface lag (SurfaceDiffusionSpec)
    surface_gain: np.ndarray | None = None
    notes: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.params.r_ohm.shape[0])

    def add_branch(self, r: np.ndarray, c: np.ndarray, alpha: np.ndarray) -> None:
        p = self.params
        p.r = np.column_stack([p.r, r])
        p.c = np.column_stack([p.c, c])
        p.alpha = np.column_stack([p.alpha, alpha])

    def ocv_offset(self, soc: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Additive OCV terms ``[T, N]`` (entropic + correction) at ``soc[T, N]``."""
        out = np.zeros_like(soc)
        if self.entropic_v_per_k is not None:
            out += self.entropic_v_per_k[None, :] * (temp_c[:, None] - self.ref_temp_c)
        if self.ocv_delta_v is not None:
            for j in range(self.n):
                out[:, j] += np.interp(soc[:, j], self.ocv_knots_soc, self.ocv_delta_v[j])
        return out


def base_mods(x: np.ndarray, profile: CellProfile, temp_c: float) -> Mods:
    """Mods for base coordinates ``x[N, 7]`` (see :mod:`service.cell.fitting`)."""
    x = np.atleast_2d(x)
    params = decode(x[:, :7], profile, temp_c, False)
    return Mods(params=params, u_h0=np.zeros(x.shape[0]), ref_temp_c=temp_c)


def arrhenius(ea_j_mol: np.ndarray, temp_c: float, ref_temp_c: float) -> np.ndarray:
    """``exp(Ea/R (1/T - 1/T_ref))`` (the law of :class:`ArrheniusSpec`)."""
    return np.exp(ea_j_mol / GAS_CONSTANT * (1.0 / (temp_c + KELVIN) - 1.0 / (ref_temp_c + KELVIN)))


def _params_at(mods: Mods, temp_c: float) -> CellParameters:
    p = mods.params.copy()
    if mods.ea_r_ohm is not None:
        p.r_ohm = p.r_ohm * arrhenius(mods.ea_r_ohm, temp_c, mods.ref_temp_c)
    if mods.ea_r_ct is not None:
        p.r[:, 0] = p.r[:, 0] * arrhenius(mods.ea_r_ct, temp_c, mods.ref_temp_c)
    if mods.ea_r_df is not None:
        p.r[:, 1] = p.r[:, 1] * arrhenius(mods.ea_r_df, temp_c, mods.ref_temp_c)
    return p


def initial_soc(
    ocv: OcvTable, v_rest: float, temp_c: float, mods: Mods | None = None
) -> np.ndarray:
    """SOC whose open-circuit voltage (with the candidates' offsets) is ``v_rest``."""
    if mods is None:
        return np.atleast_1d(ocv.soc_from_ocv(np.array([v_rest]), temp_c))
    target = v_rest - mods.u_h0
    soc = ocv.soc_from_ocv(target, temp_c)
    for _ in range(3):  # fixed point through the SOC-dependent offsets
        off = mods.ocv_offset(soc[None, :], np.array([temp_c]))[0]
        soc = ocv.soc_from_ocv(target - off, temp_c)
    return np.clip(soc, -0.2, 1.2)


def simulate_candidates(
    profile: CellProfile,
    seg: FitSegment,
    mods: Mods,
    v_rest0: float,
    memory_length: int = 16,
) -> tuple[np.ndarray, np.ndarray]:
    """Terminal voltage and SOC ``[T, N]`` of ``N`` candidates along ``seg``.

    The initial SOC of each candidate is the one its own open-circuit model puts at the
    recording's initial rest voltage ``v_rest0`` (no use of any truth column).
    """
    ocv = profile.ocv_table()
    t0 = float(seg.temperature_c[0])
    soc0 = initial_soc(ocv, v_rest0, t0, mods)
    dyn_temp = any(e is not None for e in (mods.ea_r_ohm, mods.ea_r_ct, mods.ea_r_df))
    v, soc = simulate_batch(
        profile, seg.time_s, seg.current_a, seg.temperature_c, soc0, mods.params, memory_length, mods.u_h0,
        params_at=(lambda t: _params_at(mods, t)) if dyn_temp else None,
        surface=None if mods.surface_tau_s is None else (mods.surface_tau_s, mods.surface_gain),
    )
    v = v + mods.ocv_offset(soc, seg.temperature_c)
    return v, soc
