"""Cell profile: what ``socd fit`` learns about a cell and every estimator loads.

A profile holds the capacity, OCV(SOC, T), the MTS-FOM parameters (Zeng Fig. 1) on a
temperature grid, the hysteresis of Zeng Eq. 1, and optional model *extensions* (the
physics ``socd diagnose`` can add: Arrhenius temperature laws, an extra diffusion
branch, capacity scale, current-sensor bias, Butler–Volmer kinetics, an OCV
correction, a solid-diffusion surface lag; and the resistance scales over SOC that
``socd fit --soc-resistance`` measures from HPPC pulses).  Extensions are parts of the same model,
not a fork: each one is applied by :meth:`CellProfile.parameters_at` or by
:mod:`service.cell.model`.

Files are TOML (``.toml``) or JSON (anything else), chosen by suffix.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from service.cell.ocv import OCV_V_RANGE, OcvTable, ocv_fall_problem
from service.cell.soc_dependence import SocScaleTable
from service.errors import validation_message
from service.strict_numbers import NoBooleanNumbers
from service.validation import RecordingBounds

SCHEMA_VERSION = 1
#: °C: the temperatures a profile's points may sit at (the range a recording's may lie in)
TEMP_RANGE_C = RecordingBounds().temperature_c
#: plausibility bounds of a profile's values: beyond them a value is a unit or typing error (a
#: hand-edited profile), which would otherwise run to a meaningless estimate with exit 0
PLAUSIBLE_MAX_OHM = 1.0e4  # any resistance; a coin cell's are tens of ohms, a 1 mAh micro-cell's hundreds
PLAUSIBLE_MAX_CAPACITY_AH = 1.0e5
PLAUSIBLE_CAPACITY_SCALE = (0.1, 10.0)  # effective capacity over the stated one
PLAUSIBLE_MAX_BIAS_C = 1.0  # a current-sensor offset, as a fraction of 1C
# the extensions' parameters: each several times what socd diagnose fits at most, so a saved effect
# always loads and a hand edit that would move the voltage by volts (or overflow it) does not
PLAUSIBLE_MAX_HYSTERESIS_V = 0.5  # the half-gap U_H (diagnose: 0.15 V)
PLAUSIBLE_MAX_EA_J_MOL = 1.5e5  # an activation energy (cells: 20-80 kJ/mol; diagnose: 80 kJ/mol)
PLAUSIBLE_MAX_ENTROPIC_V_K = 0.01  # dOCV/dT (cells: under 1 mV/K; diagnose: 1 mV/K)
PLAUSIBLE_MAX_OCV_CORRECTION_V = 0.5  # an additive OCV correction (diagnose: 0.15 V)
PLAUSIBLE_MAX_SURFACE_GAIN = 2.0  # a surface SOC deficit per 1C (diagnose: 0.5)
# a CPE branch: its order and its time constant (R C)^(1/order) (socd fit: orders from 0.3,
# time constants 0.1 s to about 10 days)
PLAUSIBLE_MIN_ORDER = 0.1
PLAUSIBLE_TAU_S = (1e-4, 1e8)


def ln_cpe_tau(r: float, c: float, order: float) -> float:
    """ln of a CPE branch's time constant ``(r c)^(1/order)`` (Zeng Fig. 1), taken in logs: a small
    order overflows the power; ``-inf`` for a branch without resistance or capacitance."""
    return (math.log(r) + math.log(c)) / order if r > 0 and c > 0 else -math.inf


def cpe_tau_problem(r: float, c: float, order: float, what: str) -> str | None:
    """Why the time constant ``(r c)^(1/order)`` of a CPE branch is implausible, or None."""
    ln_tau = ln_cpe_tau(r, c, order)
    lo, hi = PLAUSIBLE_TAU_S
    if not math.log(lo) <= ln_tau <= math.log(hi):
        return f"{what}'s time constant (R C)^(1/order) is outside {lo:g}-{hi:g} s"
    return None
GAS_CONSTANT = 8.314462618  # J/(mol K)
FARADAY = 96485.33212  # C/mol
KELVIN = 273.15


class _Strict(NoBooleanNumbers, BaseModel):
    # a NaN or infinite number in a profile is a corrupt file, never a value
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class OcvSpec(_Strict):
    """OCV(SOC[, T]); ``ocv_v`` has one row per temperature."""

    soc: list[float]
    temps_c: list[float] = [25.0]
    ocv_v: list[list[float]]

    @model_validator(mode="after")
    def _shape(self) -> OcvSpec:
        if len(self.ocv_v) != len(self.temps_c):
            raise ValueError(f"ocv_v has {len(self.ocv_v)} rows but temps_c has {len(self.temps_c)}")
        soc = np.array(self.soc)
        if soc.size < 2 or np.any(np.diff(soc) <= 0) or soc[0] < 0.0 or soc[-1] > 1.0:
            raise ValueError("soc must be at least 2 strictly increasing fractions in [0, 1]")
        if np.any(np.diff(self.temps_c) <= 0):
            raise ValueError(f"temps_c must be strictly increasing, got {self.temps_c}")
        for k, row in enumerate(self.ocv_v):
            if len(row) != len(self.soc):
                raise ValueError(f"ocv_v row {k} has {len(row)} values, soc has {len(self.soc)}")
            if not all(OCV_V_RANGE[0] < v <= OCV_V_RANGE[1] for v in row):
                raise ValueError(f"ocv_v row {k} ({self.temps_c[k]:g} °C) holds a voltage outside "
                                 f"({OCV_V_RANGE[0]:g}, {OCV_V_RANGE[1]:g}] V")
            if (problem := ocv_fall_problem(soc, np.array(row))) is not None:
                raise ValueError(f"ocv_v row {k} ({self.temps_c[k]:g} °C): {problem}")
        return self


class ParameterPoint(_Strict):
    """MTS-FOM parameters at one temperature (Zeng Fig. 1).  C's are CPE coefficients."""

    temp_c: float = Field(25.0, ge=TEMP_RANGE_C[0], le=TEMP_RANGE_C[1])
    r_ohm: float = Field(gt=0, le=PLAUSIBLE_MAX_OHM, description="ohmic resistance, ohm")
    r_ct: float = Field(gt=0, le=PLAUSIBLE_MAX_OHM, description="charge-transfer resistance, ohm")
    c_dl: float = Field(gt=0, description="double-layer CPE coefficient, F s^(m-1)")
    m: float = Field(ge=PLAUSIBLE_MIN_ORDER, le=1, description="charge-transfer CPE order")
    r_df: float = Field(gt=0, le=PLAUSIBLE_MAX_OHM, description="diffusion resistance, ohm")
    c_df: float = Field(gt=0, description="diffusion CPE coefficient, F s^(n-1)")
    n: float = Field(ge=PLAUSIBLE_MIN_ORDER, le=1, description="diffusion CPE order")
    i0_a: float | None = Field(
        None, gt=0, description="Butler-Volmer exchange current at this temperature, A (the apparent "
        "resistance falls as the current rises; None = linear charge transfer)",
    )

    @model_validator(mode="after")
    def _time_constants(self) -> ParameterPoint:
        for problem in (cpe_tau_problem(self.r_ct, self.c_dl, self.m, "the charge-transfer branch"),
                        cpe_tau_problem(self.r_df, self.c_df, self.n, "the diffusion branch")):
            if problem is not None:
                raise ValueError(f"{problem} at {self.temp_c:g} °C")
        return self


class HysteresisSpec(_Strict):
    """Zeng Eq. 1: ``u_h_max_v`` = U_H, ``rate`` = ε·η (dimensionless).

    ``U_h`` moves between ``-U_H`` (after discharge) and ``+U_H`` (after charge) about the
    *mean* of the two branches.  ``table_branch`` says which curve the profile's OCV table
    is: ``mean`` (the average of charge and discharge, the usual OCV table), or ``charge``
    / ``discharge`` when the only OCV test is one branch (an LFP charge curve, say).  The
    model then reads its mean OCV as the table ∓ U_H (:meth:`CellProfile.ocv_table`), so a
    cell just charged (``U_h = +U_H``) sits on a charge-branch table, not ``U_H`` above it.
    """

    u_h_max_v: float = Field(0.0, ge=0, le=PLAUSIBLE_MAX_HYSTERESIS_V)
    rate: float = Field(30.0, gt=0)
    table_branch: Literal["mean", "charge", "discharge"] = "mean"

    @property
    def branch_sign(self) -> float:
        """+1 for a charge-branch table, -1 for a discharge-branch one, 0 for the mean."""
        return {"mean": 0.0, "charge": 1.0, "discharge": -1.0}[self.table_branch]


class ArrheniusSpec(_Strict):
    """Resistances scale as exp(Ea/R (1/T - 1/T_ref)); entropic OCV slope dOCV/dT."""

    ref_temp_c: float = Field(25.0, ge=TEMP_RANGE_C[0], le=TEMP_RANGE_C[1])
    ea_r_ohm_j_mol: float = Field(0.0, ge=-PLAUSIBLE_MAX_EA_J_MOL, le=PLAUSIBLE_MAX_EA_J_MOL)
    ea_r_ct_j_mol: float = Field(0.0, ge=-PLAUSIBLE_MAX_EA_J_MOL, le=PLAUSIBLE_MAX_EA_J_MOL)
    ea_r_df_j_mol: float = Field(0.0, ge=-PLAUSIBLE_MAX_EA_J_MOL, le=PLAUSIBLE_MAX_EA_J_MOL)
    entropic_v_per_k: float = Field(0.0, ge=-PLAUSIBLE_MAX_ENTROPIC_V_K, le=PLAUSIBLE_MAX_ENTROPIC_V_K)


class BranchSpec(_Strict):
    """An extra CPE branch (e.g. a slow diffusion time constant)."""

    r: float = Field(gt=0, le=PLAUSIBLE_MAX_OHM)
    c: float = Field(gt=0)
    alpha: float = Field(1.0, ge=PLAUSIBLE_MIN_ORDER, le=1)

    @model_validator(mode="after")
    def _time_constant(self) -> BranchSpec:
        if (problem := cpe_tau_problem(self.r, self.c, self.alpha, "the extra branch")) is not None:
            raise ValueError(problem)
        return self


#: the SOC knots of an extension's table may reach a little beyond [0, 1] (a recording's counted SOC does)
SOC_KNOT_RANGE = (-0.5, 1.5)


def check_soc_knots(soc: list[float]) -> None:
    """Raise ValueError unless ``soc`` is at least two strictly increasing knots within :data:`SOC_KNOT_RANGE`."""
    if len(soc) < 2 or any(b <= a for a, b in pairwise(soc)):
        raise ValueError("soc must be strictly increasing with at least 2 points")
    lo, hi = SOC_KNOT_RANGE
    if not (lo <= soc[0] and soc[-1] <= hi):
        raise ValueError(f"soc must lie in [{lo:g}, {hi:g}], got {soc[0]:g} to {soc[-1]:g}")


class OcvCorrectionSpec(_Strict):
    """Additive correction ΔOCV(SOC) to the table."""

    soc: list[float]
    delta_v: list[float]

    @model_validator(mode="after")
    def _shape(self) -> OcvCorrectionSpec:
        check_soc_knots(self.soc)
        if len(self.delta_v) != len(self.soc):
            raise ValueError(f"delta_v has {len(self.delta_v)} values, soc has {len(self.soc)}")
        if not all(abs(d) <= PLAUSIBLE_MAX_OCV_CORRECTION_V for d in self.delta_v):
            raise ValueError(f"delta_v holds a correction beyond ±{PLAUSIBLE_MAX_OCV_CORRECTION_V:g} V")
        return self


class SurfaceDiffusionSpec(_Strict):
    """Solid-diffusion lag: the particle *surface* SOC trails the bulk (Coulomb-counted) SOC.

    ``x`` = bulk − surface SOC follows ``τ dx/dt = gain · I/Q − x`` (``I/Q`` the C-rate,
    positive = discharge; ``Q`` the capacity after ``capacity_scale``), and the OCV is read
    at the surface: ``OCV(SOC − x)``.  The overpotential is therefore ``≈ dOCV/dSOC · x``:
    it builds over ``τ``, relaxes over ``τ`` in a rest, and is large where the OCV is
    steep (low SOC on NMC) -- the SOC dependence a constant-R branch cannot give.
    ``gain`` is the steady-state surface deficit per 1C (fraction of SOC).  ``x`` starts
    at 0 (a rested cell).  Simulated by :mod:`service.cell.model` and
    :func:`service.cell.trajectory.simulate_batch`; the paper's pipeline
    (:class:`service.estimators.pipeline.PackEstimator`: ``fomiukf``, ``foukf``,
    ``fom-single-scale`` and the service) propagates ``x`` from the measured current and
    reads its OCV at the surface.  The 2-RC EKF baseline ignores the term.
    """

    tau_s: float = Field(gt=0, le=1e7, description="surface-bulk relaxation time constant, s")
    gain: float = Field(ge=0, le=PLAUSIBLE_MAX_SURFACE_GAIN,
                        description="steady-state surface SOC deficit per 1C, fraction")


class SocResistanceSpec(_Strict):
    """Resistance scales over SOC and temperature (:mod:`service.cell.soc_dependence`):
    ``r_ohm_scale`` multiplies ``R_ohm``; ``r_pol_scale`` multiplies ``R_ct`` and ``R_df``
    (and divides their ``C``, so the branch time constants stay).  Rows per temperature."""

    soc: list[float]
    temps_c: list[float]
    r_ohm_scale: list[list[float]]
    r_pol_scale: list[list[float]]

    @model_validator(mode="after")
    def _shape(self) -> SocResistanceSpec:
        check_soc_knots(self.soc)
        if len(set(self.temps_c)) != len(self.temps_c):
            raise ValueError(f"duplicate temperatures: {self.temps_c}")
        if not self.temps_c or any(b <= a for a, b in pairwise(self.temps_c)):
            raise ValueError(f"temps_c must be increasing with at least 1 temperature, got {self.temps_c}")
        for name in ("r_ohm_scale", "r_pol_scale"):
            rows = getattr(self, name)
            if len(rows) != len(self.temps_c):
                raise ValueError(f"{name} has {len(rows)} rows but temps_c has {len(self.temps_c)}")
            for k, row in enumerate(rows):
                if len(row) != len(self.soc):
                    raise ValueError(f"{name} row {k} has {len(row)} values, soc has {len(self.soc)}")
                if not all(0.0 < v < 100.0 and np.isfinite(v) for v in row):
                    raise ValueError(f"{name} row {k} holds a scale outside (0, 100)")
        return self


class Extensions(_Strict):
    """Model parts beyond the base MTS-FOM (added by ``socd diagnose``, or ``soc_resistance``
    by ``socd fit --soc-resistance``)."""

    current_bias_a: float = 0.0
    capacity_scale: float = Field(1.0, ge=PLAUSIBLE_CAPACITY_SCALE[0], le=PLAUSIBLE_CAPACITY_SCALE[1])
    arrhenius: ArrheniusSpec | None = None
    extra_branches: list[BranchSpec] = []
    kinetics_i0_a: float | None = Field(None, gt=0, description="Butler-Volmer exchange current")
    ocv_correction: OcvCorrectionSpec | None = None
    diffusion_surface: SurfaceDiffusionSpec | None = None
    soc_resistance: SocResistanceSpec | None = None


def sorted_by_temperature(points: list, what: str) -> list:
    """``points`` (anything with ``temp_c``) sorted by temperature; a repeated temperature is an
    error naming ``what``."""
    temps = [p.temp_c for p in points]
    if len(set(temps)) != len(temps):
        raise ValueError(f"duplicate temperatures in {what}: {temps}")
    return sorted(points, key=lambda p: p.temp_c)


class Ecm2RcPoint(_Strict):
    """Textbook 2-RC parameters at one temperature (``V = OCV - R0 I - U1 - U2``)."""

    temp_c: float = Field(25.0, ge=TEMP_RANGE_C[0], le=TEMP_RANGE_C[1])
    r0: float = Field(gt=0, le=PLAUSIBLE_MAX_OHM, description="ohmic resistance, ohm")
    r1: float = Field(ge=0, le=PLAUSIBLE_MAX_OHM, description="fast RC branch resistance, ohm")
    tau1_s: float = Field(gt=0, description="fast RC branch time constant, s")
    r2: float = Field(ge=0, le=PLAUSIBLE_MAX_OHM, description="slow RC branch resistance, ohm")
    tau2_s: float = Field(gt=0, description="slow RC branch time constant, s")
    fit_rmse_mv: float | None = Field(None, ge=0, description="fit RMSE on the characterisation data, mV")


class Ecm2RcSpec(_Strict):
    """The textbook 2-RC model fitted beside the fractional one by ``socd fit``
    (:mod:`service.characterisation.ecm2rc_fit`), with its own OCV: what the ``ecm2rc-ekf``
    baseline runs on, so every evaluation shows the bar a 200-line EKF sets."""

    ocv: OcvSpec
    points: list[Ecm2RcPoint] = Field(min_length=1)

    @field_validator("points")
    @classmethod
    def _sorted(cls, v: list[Ecm2RcPoint]) -> list[Ecm2RcPoint]:
        return sorted_by_temperature(v, "ecm2rc points")

    def ocv_table(self) -> OcvTable:
        return OcvTable.from_points(np.array(self.ocv.soc), np.array(self.ocv.ocv_v), np.array(self.ocv.temps_c))

    def fit_rmse_v_at(self, temp_c: np.ndarray) -> np.ndarray | None:
        """The fit RMSE (V) at ``temp_c [N]``, linear in T between the fitted temperatures and held
        beyond them; None when a point has none (a profile written by hand or before it was stored)."""
        if any(p.fit_rmse_mv is None for p in self.points):
            return None
        grid = np.array([p.temp_c for p in self.points])
        rmse = np.array([p.fit_rmse_mv for p in self.points]) / 1000.0
        return np.interp(np.atleast_1d(np.asarray(temp_c, dtype=float)), grid, rmse)

    def at(self, temp_c: np.ndarray) -> dict[str, np.ndarray]:
        """``r0 [N]``, ``r [N, 2]``, ``tau [N, 2]`` at ``temp_c [N]``: log-linear in 1/T between
        the fitted temperatures (:func:`arrhenius_interp`), like the fractional parameters."""
        temp = np.atleast_1d(np.asarray(temp_c, dtype=float))
        grid = np.array([p.temp_c for p in self.points])

        def interp(name: str) -> np.ndarray:
            vals = np.maximum(np.array([getattr(p, name) for p in self.points]), 1e-9)
            return np.exp(arrhenius_interp(temp, grid, np.log(vals)))

        return {"r0": interp("r0"), "r": np.stack([interp("r1"), interp("r2")], axis=-1),
                "tau": np.stack([interp("tau1_s"), interp("tau2_s")], axis=-1)}


class CellProfile(_Strict):
    """Everything known about one cell type; loaded by estimators and the service."""

    schema_version: int = Field(SCHEMA_VERSION, description="profile format; a later one is from a newer socd, "
                                "which this one cannot read")
    name: str = "cell"
    capacity_ah: float = Field(gt=0, le=PLAUSIBLE_MAX_CAPACITY_AH)
    #: the G-L short memory the parameters were fitted with, in seconds (``L`` samples × the fit
    #: data's sample period): the estimators run the model with ``L = span / h`` at their own
    #: sample period ``h`` (:mod:`service.cell.memory`); None (a profile from before): ``L`` as set
    memory_span_s: float | None = Field(None, gt=0)
    ocv: OcvSpec
    parameters: list[ParameterPoint] = Field(min_length=1)
    hysteresis: HysteresisSpec = HysteresisSpec()
    extensions: Extensions = Extensions()
    #: the textbook 2-RC model fitted from the same recordings (``ecm2rc-ekf`` runs on it)
    ecm2rc: Ecm2RcSpec | None = None
    notes: dict[str, str] = {}

    @field_validator("schema_version")
    @classmethod
    def _known_version(cls, v: int) -> int:
        if not 1 <= v <= SCHEMA_VERSION:
            raise ValueError(f"schema_version {v} is not one this socd reads (1..{SCHEMA_VERSION}): "
                             "a profile from a newer socd, or a corrupt file")
        return v

    @field_validator("parameters")
    @classmethod
    def _sorted(cls, v: list[ParameterPoint]) -> list[ParameterPoint]:
        ordered = sorted_by_temperature(v, "parameters")
        with_i0 = [p.i0_a is not None for p in v]
        if any(with_i0) and not all(with_i0):
            raise ValueError("i0_a must be given at every temperature or at none "
                             f"(given at {[p.temp_c for p in v if p.i0_a is not None]})")
        return ordered

    @model_validator(mode="after")
    def _plausible_bias(self) -> CellProfile:
        """A current-sensor offset beyond :data:`PLAUSIBLE_MAX_BIAS_C` × 1C is no sensor offset."""
        bias = self.extensions.current_bias_a
        if not abs(bias) <= PLAUSIBLE_MAX_BIAS_C * self.capacity_ah:
            raise ValueError(f"extensions.current_bias_a {bias:g} A is beyond {PLAUSIBLE_MAX_BIAS_C:g}C of this "
                             f"{self.capacity_ah:g} Ah cell: a current-sensor offset that size is a unit or typing error")
        return self

    @model_validator(mode="after")
    def _kinetic_floor(self) -> CellProfile:
        """``R_ohm`` must hold the Butler–Volmer term's linear drop (see :func:`kinetic_floor_ohm`)."""
        for k, p in enumerate(self.parameters):
            i0 = self.extensions.kinetics_i0_a if self.extensions.kinetics_i0_a is not None else p.i0_a
            if i0 is None:
                continue
            floor = kinetic_floor_ohm(i0, p.temp_c, self.min_r_ohm_scale(p.temp_c))
            if p.r_ohm < floor * (1.0 - 1e-6):
                raise ValueError(
                    f"parameters[{k}] ({p.temp_c:g} °C): r_ohm {p.r_ohm * 1e3:.2f} mΩ is below the linear "
                    f"Butler-Volmer drop 2RT/F/(2 i0) = {floor * 1e3:.2f} mΩ of i0 {i0:.4g} A (after the lowest "
                    "SOC scale of R_ohm): the model's voltage would rise above the OCV under a large discharge. "
                    "Refit the profile with this version's socd fit / socd diagnose, or raise r_ohm"
                )
        return self

    def min_r_ohm_scale(self, temp_c: float | np.ndarray) -> float:
        """Lowest ``R_ohm`` SOC scale at ``temp_c``, or over every temperature of an array of them
        (1 without a SOC-resistance table)."""
        table = self.soc_scale_table()
        if table is None:
            return 1.0
        soc, temps = np.meshgrid(np.linspace(0.0, 1.0, 201), np.atleast_1d(np.asarray(temp_c, dtype=float)))
        g_ohm, _ = table(soc, temps)
        return float(min(np.min(g_ohm), 1.0))

    # -- derived objects ----------------------------------------------------------------
    def beyond_fit(self, temp_c: np.ndarray) -> np.ndarray:
        """Where ``temp_c`` lies more than :data:`FIT_TEMPERATURE_MARGIN_K` outside the temperatures
        this profile's parameters were fitted at (element-wise; NaN is not beyond): there the
        resistances follow the end segment's Arrhenius slope (:meth:`parameters_at`), which no data
        checked, up to :data:`EXTRAPOLATE_C` K, and are held beyond."""
        fitted = [p.temp_c for p in self.parameters]
        t = np.asarray(temp_c, dtype=float)
        return (t < min(fitted) - FIT_TEMPERATURE_MARGIN_K) | (t > max(fitted) + FIT_TEMPERATURE_MARGIN_K)

    def temperatures_beyond_fit(self, temp_c: np.ndarray) -> str | None:
        """A sentence when a recording's median temperature ``temp_c`` is :meth:`beyond_fit`, else
        None.  The median, not the extremes: a drive heats the cell by several kelvin."""
        fitted = [p.temp_c for p in self.parameters]
        median = float(np.median(temp_c))
        if not self.beyond_fit(np.array(median)):
            return None
        span = f"{fitted[0]:g} °C" if len(fitted) == 1 else f"{min(fitted):g} to {max(fitted):g} °C"
        return (f"recorded at {median:.0f} °C (median), more than {FIT_TEMPERATURE_MARGIN_K:g} K outside the {span} "
                f"profile {self.name!r} was fitted at: its parameters there are extrapolated (and held beyond "
                f"{EXTRAPOLATE_C:g} K)")

    @property
    def effective_capacity_ah(self) -> float:
        """The capacity charge is counted with: ``capacity_ah`` times the ``capacity_scale``
        extension (a capacity fade named by ``socd diagnose``)."""
        return self.capacity_ah * self.extensions.capacity_scale

    def ocv_table(self) -> OcvTable:
        """The model's OCV(SOC, T): the mean of the branches (``hysteresis.table_branch``),
        plus the ``ocv_correction`` extension."""
        ocv_v = np.array(self.ocv.ocv_v) - self.hysteresis.branch_sign * self.hysteresis.u_h_max_v
        table = OcvTable.from_points(np.array(self.ocv.soc), ocv_v, np.array(self.ocv.temps_c))
        corr = self.extensions.ocv_correction
        if corr is not None:
            delta = np.interp(table.soc_grid, corr.soc, corr.delta_v)
            table = OcvTable.from_points(table.soc_grid, table.ocv_v + delta[None, :], table.temps_c)
        return table

    def soc_scale_table(self) -> SocScaleTable | None:
        """The resistance scales over SOC and T, or ``None`` (flat in SOC)."""
        spec = self.extensions.soc_resistance
        if spec is None:
            return None
        return SocScaleTable.from_points(spec.soc, spec.temps_c, spec.r_ohm_scale, spec.r_pol_scale)

    def parameters_at(self, temp_c: np.ndarray | float, n_cells: int | None = None) -> CellParameters:
        """Parameters for each cell at its temperature (log-linear in T between grid points)."""
        temp = np.atleast_1d(np.asarray(temp_c, dtype=float))
        if n_cells is not None and temp.size == 1:
            temp = np.full(n_cells, float(temp[0]))
        grid = np.array([p.temp_c for p in self.parameters])

        def interp(name: str, log: bool) -> np.ndarray:
            vals = np.array([getattr(p, name) for p in self.parameters])
            if log:
                return np.exp(arrhenius_interp(temp, grid, np.log(vals)))
            return np.interp(temp, grid, vals)

        r_ohm, r_ct, r_df = interp("r_ohm", True), interp("r_ct", True), interp("r_df", True)
        ones = np.ones_like(temp)
        if self.extensions.kinetics_i0_a is not None:
            # added by socd diagnose on top of the base model: it takes precedence
            i0 = self.extensions.kinetics_i0_a * ones
        elif self.parameters[0].i0_a is not None:
            # characterised per temperature: between fitted temperatures the two resistances a pulse
            # test observes are interpolated, not R_ohm and i0 themselves. Per-temperature fits trade
            # R_ohm against i0, and a linear point beside one whose whole drop is Butler-Volmer would
            # otherwise interpolate to less resistance than either, at every current
            r_ohm, i0 = self.kinetics_at(temp)
        else:
            i0 = np.inf * ones
        arr = self.extensions.arrhenius
        if arr is not None:
            # Arrhenius scaling around the nearest table temperature's value
            ref = arr.ref_temp_c
            inv = 1.0 / (temp + KELVIN) - 1.0 / (ref + KELVIN)
            r_ohm = r_ohm * np.exp(arr.ea_r_ohm_j_mol / GAS_CONSTANT * inv)
            r_ct = r_ct * np.exp(arr.ea_r_ct_j_mol / GAS_CONSTANT * inv)
            r_df = r_df * np.exp(arr.ea_r_df_j_mol / GAS_CONSTANT * inv)
        extra = self.extensions.extra_branches
        r = np.stack([r_ct, r_df] + [np.full_like(temp, b.r) for b in extra], axis=-1)
        c = np.stack([interp("c_dl", True), interp("c_df", True)] + [np.full_like(temp, b.c) for b in extra], axis=-1)
        alpha = np.stack([interp("m", False), interp("n", False)] + [np.full_like(temp, b.alpha) for b in extra], axis=-1)
        return CellParameters(
            r_ohm=r_ohm,
            r=r,
            c=c,
            alpha=alpha,
            u_h_max=self.hysteresis.u_h_max_v * ones,
            hyst_rate=self.hysteresis.rate * ones,
            capacity_ah=self.effective_capacity_ah * ones,
            current_bias_a=self.extensions.current_bias_a * ones,
            kinetics_i0_a=i0,
        )

    def kinetics_at(self, temp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``R_ohm`` and ``i0`` between fitted temperatures (a profile with ``i0_a`` per point):
        the small-current resistance ``R_ohm`` and the apparent resistance at 1C (drop over
        current, :func:`apparent_resistance_ohm`) are each interpolated like the other resistances
        and held beyond the fitted temperatures, and ``i0`` is the exchange current that gives both
        (:func:`exchange_current_matching`), raised where needed to keep ``R_ohm`` above the linear
        Butler–Volmer drop (:func:`kinetic_floor_ohm`).  At a fitted temperature this returns the
        fitted pair."""
        grid = np.array([p.temp_c for p in self.parameters])
        i0_g = np.array([p.i0_a for p in self.parameters])
        r_small = np.array([p.r_ohm for p in self.parameters])
        one_c = self.effective_capacity_ah
        r_one_c = apparent_resistance_ohm(r_small, i0_g, one_c, grid)
        # held beyond the fitted range: a fit's R_ohm/i0 trade moves the end segments either way
        inside = np.clip(temp, grid.min(), grid.max())
        small = np.exp(arrhenius_interp(inside, grid, np.log(r_small)))
        if np.any(r_one_c <= 0):
            # an unfloored point whose drop falls at 1C: nothing observable to match; log-interpolate i0
            return small, np.exp(arrhenius_interp(inside, grid, np.log(i0_g)))
        large = np.exp(arrhenius_interp(inside, grid, np.log(r_one_c)))
        i0 = np.clip(exchange_current_matching(small, large, one_c, inside), i0_g.min(), i0_g.max())
        # never below the floor every fitted point keeps (R_ohm holds the linear drop, _kinetic_floor),
        # which the two interpolations alone do not guarantee: the 1C match gives way there
        return small, np.maximum(i0, floor_exchange_current_a(small, temp, self.min_r_ohm_scale(grid)))

    @property
    def n_branches(self) -> int:
        return 2 + len(self.extensions.extra_branches)


#: how far beyond the fitted temperatures parameters are extrapolated
EXTRAPOLATE_C = 15.0
#: a recording whose median temperature lies further than this beyond the fitted temperatures is
#: named in a warning (:meth:`CellProfile.temperatures_beyond_fit`)
FIT_TEMPERATURE_MARGIN_K = 10.0


def kinetic_voltage_v(temp_c: np.ndarray | float) -> np.ndarray:
    """``2RT/F``, the voltage scale of the symmetric Butler–Volmer term
    (:func:`service.cell.model.kinetic_overpotential`)."""
    return 2.0 * GAS_CONSTANT * (np.asarray(temp_c, dtype=float) + KELVIN) / FARADAY


def kinetic_linear_ohm(i0_a: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
    """Small-current resistance of the Butler–Volmer drop, ``2RT/F / (2 i0)``: the linear part
    that a ``--kinetics`` fit keeps in ``R_ohm`` (:func:`service.cell.model.kinetic_overpotential`
    subtracts it again)."""
    return kinetic_voltage_v(temp_c) / (2.0 * np.asarray(i0_a))


def floor_exchange_current_a(r_ohm: np.ndarray, temp_c: np.ndarray, min_scale: float = 1.0) -> np.ndarray:
    """The smallest ``i0`` whose linear drop ``R_ohm`` still holds: :func:`kinetic_floor_ohm` solved
    for ``i0``."""
    return kinetic_voltage_v(temp_c) / (2.0 * np.asarray(r_ohm) * min_scale)


def apparent_resistance_ohm(r_ohm: np.ndarray, i0_a: np.ndarray, current_a: float,
                            temp_c: np.ndarray) -> np.ndarray:
    """Instantaneous drop over current at ``current_a`` of ``R_ohm`` with the Butler–Volmer term
    (:func:`service.cell.model.kinetic_overpotential`): ``R_ohm − 2RT/F (y − asinh y) / I``,
    ``y = I / (2 i0)``."""
    y = current_a / (2.0 * np.asarray(i0_a, dtype=float))
    return r_ohm - kinetic_linear_ohm(i0_a, temp_c) * (y - np.arcsinh(y)) / y


#: bisection steps of :func:`exchange_current_matching` over y = I/(2 i0) in [1e-6, 1e6] (log):
#: 2^-60 of 27.6 decades
_MATCH_STEPS = 60


def exchange_current_matching(r_small: np.ndarray, r_large: np.ndarray, current_a: float,
                              temp_c: np.ndarray) -> np.ndarray:
    """The ``i0`` whose Butler–Volmer term, with ``R_ohm = r_small``, gives apparent resistance
    ``r_large`` at ``current_a`` (:func:`apparent_resistance_ohm`): solves
    ``2RT/F (y − asinh y) / I = r_small − r_large`` for ``y = I / (2 i0)``, increasing in ``y``.
    ``r_large ≥ r_small`` (no drop in resistance) gives the largest ``i0`` searched."""
    vt = kinetic_voltage_v(temp_c)
    target = np.maximum(np.asarray(r_small) - np.asarray(r_large), 0.0) * current_a / vt
    lo, hi = np.full(target.shape, math.log(1e-6)), np.full(target.shape, math.log(1e6))
    for _ in range(_MATCH_STEPS):
        mid = 0.5 * (lo + hi)
        y = np.exp(mid)
        above = y - np.arcsinh(y) > target
        hi, lo = np.where(above, mid, hi), np.where(above, lo, mid)
    return current_a / (2.0 * np.exp(0.5 * (lo + hi)))


def kinetic_floor_ohm(i0_a, temp_c, min_scale: float = 1.0):
    """Smallest ``R_ohm`` a Butler–Volmer cell may have: the linear drop ``2RT/F / (2 i0)``
    divided by the lowest SOC scale of ``R_ohm``.  The model's instantaneous drop is
    ``R_ohm·g·I + 2RT/F (asinh(I/2i0) − I/2i0)`` (:func:`service.cell.model.kinetic_overpotential`);
    it grows with the discharge current only while ``R_ohm·g ≥ 2RT/F / (2 i0)``, else a large
    enough discharge lifts the terminal voltage above the OCV."""
    return kinetic_linear_ohm(i0_a, temp_c) / min_scale


def ohmic_floor_ohm(i0_a, temp_c, min_scale: float = 1.0, pure_ohm: float = 0.0):
    """Smallest ``R_ohm`` a fit may give: ``pure_ohm`` (the electrolyte's and contacts' part, which
    no Butler–Volmer term replaces) on top of :func:`kinetic_floor_ohm` (0 without an ``i0_a``)."""
    kinetic = 0.0 if i0_a is None else kinetic_floor_ohm(i0_a, temp_c, min_scale)
    return kinetic + pure_ohm


def lift_to_ohmic_floor(point: ParameterPoint, i0_a: float | None, min_scale: float = 1.0,
                        pure_ohm: float = 0.0) -> ParameterPoint:
    """``point`` with ``R_ohm`` raised to :func:`ohmic_floor_ohm` at its own temperature
    (unchanged when already above)."""
    floor = float(ohmic_floor_ohm(i0_a, point.temp_c, min_scale, pure_ohm))
    return point if point.r_ohm >= floor else point.model_copy(update={"r_ohm": floor})


def arrhenius_interp(temp_c: np.ndarray, grid_c: np.ndarray, log_values: np.ndarray) -> np.ndarray:
    """Piecewise-linear in 1/T (Arrhenius) between fitted temperatures; beyond them the
    end segment is extended by at most :data:`EXTRAPOLATE_C`, then held."""
    if grid_c.size == 1:
        return np.full(np.shape(temp_c), log_values[0])
    inv = 1.0 / (grid_c + KELVIN)  # decreasing with T
    t = np.clip(temp_c, grid_c[0] - EXTRAPOLATE_C, grid_c[-1] + EXTRAPOLATE_C)
    x = 1.0 / (t + KELVIN)
    out = np.interp(x, inv[::-1], log_values[::-1])
    lo_slope = (log_values[1] - log_values[0]) / (inv[1] - inv[0])
    hi_slope = (log_values[-1] - log_values[-2]) / (inv[-1] - inv[-2])
    out = np.where(x > inv[0], log_values[0] + lo_slope * (x - inv[0]), out)
    out = np.where(x < inv[-1], log_values[-1] + hi_slope * (x - inv[-1]), out)
    return out


@dataclass
class CellParameters:
    """Per-cell model parameters as arrays (``[N]`` or ``[N, B]`` for the CPE branches).

    Branch 0 is charge transfer (R_ct, C_dl, m), branch 1 diffusion (R_df, C_df, n),
    further branches come from extensions.
    """

    r_ohm: np.ndarray
    r: np.ndarray
    c: np.ndarray
    alpha: np.ndarray
    u_h_max: np.ndarray
    hyst_rate: np.ndarray
    capacity_ah: np.ndarray
    current_bias_a: np.ndarray
    kinetics_i0_a: np.ndarray

    def copy(self) -> CellParameters:
        return CellParameters(**{k: np.array(v, copy=True) for k, v in self.__dict__.items()})

    def take(self, idx: np.ndarray | slice) -> CellParameters:
        return CellParameters(**{k: np.array(v[idx], copy=True) for k, v in self.__dict__.items()})


class ProfileError(Exception):
    """A cell profile file that cannot be used; the message names the file and field."""


def load_profile(path: str | Path) -> CellProfile:
    path = Path(path)
    from service.validation import InputFileError, read_text

    try:
        text = read_text(path, "cell profile")
    except InputFileError as exc:  # a missing one is named with the bundled profiles (read_text)
        raise ProfileError(str(exc)) from None
    try:
        raw = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ProfileError(f"{path}: not valid {'TOML' if path.suffix == '.toml' else 'JSON'}: {exc}") from exc
    try:
        # strict: a number written as a string or a boolean is a mistake, not a value
        return CellProfile.model_validate(raw, strict=True)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = ".".join(str(p) for p in first["loc"])
        where = f"field '{field}': " if field else ""
        raise ProfileError(f"{path}: {where}{validation_message(first)}") from exc


#: significant digits a saved profile keeps of each float: what a fit determines, and no binary
#: float noise (``0.17500000000000002`` is written ``0.175``); the profile in memory keeps all of them
SAVED_SIGNIFICANT_DIGITS = 12


def rounded_floats(value: Any, digits: int = SAVED_SIGNIFICANT_DIGITS) -> Any:
    """``value`` with every float, through dicts and lists of any depth, rounded to ``digits``
    significant digits (a new structure; ints, bools, strings and None as they are)."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}")
    if isinstance(value, dict):
        return {k: rounded_floats(v, digits) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [rounded_floats(v, digits) for v in value]
    return value


def save_profile(profile: CellProfile, path: str | Path) -> None:
    """Write ``profile`` as TOML (``.toml``) or JSON (else), floats to :data:`SAVED_SIGNIFICANT_DIGITS`
    significant digits, through a temporary file beside it."""
    path = Path(path)
    data = rounded_floats(profile.model_dump(mode="json", exclude_none=True))
    if path.suffix == ".toml":
        import tomli_w

        text = tomli_w.dumps(data)
    else:
        text = json.dumps(data, indent=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
