"""Integer-order 2-RC extended Kalman filter: the classic baseline (Plett 2004, Part 3).

Model, per cell, in this project's convention (current positive = discharge)::

    SOC_k = SOC_{k-1} - I_k dt_k / (3600 Q)                  (Zeng Eq. 4, h and 3600 restored)
    U_b,k = a_b U_b,k-1 + R_b (1 - a_b) I_k,                    (Hu & Wang Eq. 2, exact for a
            a_b = exp(-dt_k / τ_b)                             current held over (t_{k-1}, t_k])
    V_k   = OCV(SOC_k, T_k) - R0 I_k - U_1,k - U_2,k - η_kin(I_k, T_k)   (Zeng Eq. 6 without U_h)

with state ``x = [SOC, U_1, U_2]`` and the actual interval ``dt_k`` of every sample.

Parameters: a profile from ``socd fit`` carries the textbook 2-RC model fitted from the same
recordings (:class:`service.cell.profile.Ecm2RcSpec`: its own OCV, ``R0``, ``R_b``, ``τ_b``
per temperature); the filter runs on that, as a user who wrote a 2-RC EKF and characterised
it would, and ignores the fractional model and its extensions except the capacity scale.
A profile without one (written before it existed, or by hand) falls back to
what a user would read off the fractional parameters (:meth:`CellProfile.parameters_at`
at the recorded temperature, refreshed when a cell's temperature has moved more than
``temp_update_c``): ``R0 = r_ohm``, branch ``b``: ``R_b = r[b]``, ``τ_b = (r c)^(1/α)`` —
the characteristic time of the CPE branch (for ``α = 1`` exactly ``R C``).  Capacity
includes the ``capacity_scale`` extension and the ``current_bias_a`` extension is
subtracted from the measured current.  A profile fitted with Butler–Volmer kinetics
(``socd fit --kinetics``) keeps the linear part of the charge-transfer drop in ``R0`` and
the fall of the apparent resistance at high current in ``η_kin`` (a known function of the
current, :func:`service.cell.model.kinetic_overpotential`, so the Jacobian is unchanged):
the baseline reads the same profile as the pipeline, including the resistance scales over
SOC (``socd fit --soc-resistance``; ``R0`` and ``R_b`` scaled at the prior SOC, ``τ_b``
kept).  Hysteresis, extra branches, the entropic OCV term and the solid-diffusion
surface lag are not part of a 2-RC EKF and are ignored (the pipeline reads all four).

Noise model (all keyword arguments of the constructors):

* process: a current-sensor error of ``current_noise_c`` × 1C (1σ, held over a step) enters
  SOC and both RC voltages through the input column ``G = [-dt/3600Q, R_1(1-a_1),
  R_2(1-a_2)]`` (``Q_k = σ_I² G Gᵀ``), plus random walks of ``soc_noise_per_sqrt_s``
  and ``u_noise_v_per_sqrt_s`` per √s for what the model leaves out;
* measurement: ``voltage_noise_v`` (1σ) — sensor noise plus OCV-table and model error;
* initial: SOC standard deviation ``soc0_std`` (0.2, the evaluation's initial error),
  RC voltages 0 ± ``u0_std_v`` (recordings start at rest).

The covariance update is the Joseph form ``P = (I-KH) P (I-KH)ᵀ + K R Kᵀ`` and ``P``
is re-symmetrised each step, so it stays symmetric positive definite.  SOC is
clipped to ``soc_clip`` after each update.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Literal

import numpy as np
from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass

from service.cell.model import kinetic_overpotential
from service.cell.ocv import OcvTable
from service.cell.profile import CellProfile
from service.cell.units import SECONDS_PER_HOUR
from service.estimators.adaptive_noise import AdaptiveNoise
from service.estimators.base import EstimateTrace
from service.estimators.settings import current_sigma_a
from service.recording import Recording

N_STATES = 3


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid", allow_inf_nan=False))
class EkfTuning:
    """Noise constants and guards of the 2-RC EKF.

    One set of defaults serves every cell.  The current-sensor σ is chosen as the pipeline's
    settings are, leave-one-cell-out over the shared cells pooled with and without a 1 % current
    offset (``loco_ekf_current_noise`` in docs/results/tuning.md).  The 10 mV voltage noise stands
    mostly for OCV-table and model error, not for the sensor.  The RC-state walk ``u_noise_v_per_sqrt_s`` is swept beside
    the pipeline's branch walk in docs/results/tuning.md (``research.nested_tuning``); pooled over
    the scored files the default is as good as the per-cell choices.
    """

    voltage_noise_v: float = Field(0.01, gt=0, le=1)
    #: current-sensor σ as a fraction of 1C (scale-free, as the pipeline's ``current_noise_c``)
    current_noise_c: float = Field(0.009, ge=0, le=10)
    #: the same σ in A, overriding ``current_noise_c`` when set
    current_noise_a: float | None = Field(None, ge=0, le=1000)
    soc_noise_per_sqrt_s: float = Field(1e-5, ge=0, le=1)
    u_noise_v_per_sqrt_s: float = Field(2e-4, ge=0, le=1)
    soc0_std: float = Field(0.2, gt=0, le=1)
    u0_std_v: float = Field(0.005, ge=0, le=1)
    temp_update_c: float = Field(0.5, gt=0, le=100)
    #: covariance matching of the measurement noise over about this many samples (0 = off);
    #: the same adaptive rule as the pipeline's ``adaptive_noise_samples``, so the baseline
    #: gets every tuning aid the pipeline gets
    adaptive_noise_samples: int = Field(300, ge=0, le=100000)
    #: 'uniform' or 'load' (see service.estimators.adaptive_noise), as the pipeline's setting
    adaptive_noise_shape: Literal["uniform", "load"] = "uniform"
    #: the learned variance's correlation inflation cap, as the pipeline's setting (1 = off)
    adaptive_noise_correlation_cap: float = Field(1.0, ge=1, le=1000)
    #: SOC in [0, 1] (DESIGN), the same bound as the pipeline's filter
    soc_clip: tuple[float, float] = (0.0, 1.0)
    #: the measurement Jacobian's dOCV/dSOC: 0 = the table's slope at the estimate (the textbook
    #: linearisation); > 0 = the secant over ± this much SOC, which reads a fitted table's flat
    #: steps (a monotone fit's active constraint) as the rise across them
    #: (``loco_ekf_ocv_slope`` in docs/results/tuning.md)
    ocv_slope_span_soc: float = Field(0.0, ge=0, le=0.5)


def ecm_parameters(profile: CellProfile, temp_c: np.ndarray) -> dict[str, np.ndarray]:
    """2-RC parameters at ``temp_c [N]``.

    Returns ``r0 [N]``, ``r [N,2]``, ``tau [N,2]``, ``capacity [N]``, ``bias [N]`` and the
    Butler–Volmer exchange current ``i0 [N]`` (infinite: no kinetic term).

    ``τ = (R C)^(1/α)``: the CPE branch's characteristic time (its impedance
    ``R / (1 + R C (jω)^α)`` has its corner at ``ω = (R C)^(-1/α)``).
    """
    temp = np.atleast_1d(np.asarray(temp_c, dtype=float))
    if profile.ecm2rc is not None:
        own = profile.ecm2rc.at(temp)
        ones = np.ones_like(temp)
        return own | {"capacity": profile.capacity_ah * profile.extensions.capacity_scale * ones,
                      "bias": np.zeros_like(temp), "i0": np.inf * ones}
    p = profile.parameters_at(temp)
    r = p.r[:, :2]
    tau = np.power(p.r[:, :2] * p.c[:, :2], 1.0 / p.alpha[:, :2])
    return {"r0": p.r_ohm, "r": r, "tau": tau, "capacity": p.capacity_ah, "bias": p.current_bias_a,
            "i0": p.kinetics_i0_a}


class Ecm2RcEkfBank:
    """The 2-RC EKF for ``N`` cells at once: ``x [N, 3]``, ``P [N, 3, 3]``.

    Drive it with :meth:`step` one sample at a time (online), or use
    :class:`Ecm2RcEkf` for a whole recording.
    """

    def __init__(
        self,
        profile: CellProfile,
        soc0: np.ndarray | float,
        temp0_c: np.ndarray | float,
        n_cells: int | None = None,
        tuning: EkfTuning | None = None,
        ocv: OcvTable | None = None,
    ) -> None:
        self.profile = profile
        self.tuning = tuning or EkfTuning()
        textbook = profile.ecm2rc is not None
        self.ocv = ocv if ocv is not None else (profile.ecm2rc.ocv_table() if textbook else profile.ocv_table())
        shape = np.broadcast_shapes(np.shape(soc0), np.shape(temp0_c), (n_cells or 1,))
        n = shape[0] if shape else 1
        self.x = np.zeros((n, N_STATES))
        self.x[:, 0] = np.broadcast_to(np.asarray(soc0, dtype=float), (n,))
        t = self.tuning
        self.P = np.broadcast_to(
            np.diag([t.soc0_std**2, t.u0_std_v**2, t.u0_std_v**2]), (n, 3, 3)
        ).copy()
        self._temp_params = np.broadcast_to(np.asarray(temp0_c, dtype=float), (n,)).copy()
        self._params = ecm_parameters(profile, self._temp_params)
        #: any Butler–Volmer term in the profile (at some temperature, or the extension)
        self._kinetic = not textbook and bool(profile.extensions.kinetics_i0_a is not None
                                              or any(pt.i0_a is not None for pt in profile.parameters))
        self._soc_scale = None if textbook else profile.soc_scale_table()
        self.noise = AdaptiveNoise(n, max(t.adaptive_noise_samples, 1), t.adaptive_noise_shape,  # type: ignore[arg-type]
                                   t.adaptive_noise_correlation_cap)

    @property
    def n_cells(self) -> int:
        return self.x.shape[0]

    @property
    def soc(self) -> np.ndarray:
        return self.x[:, 0]

    @property
    def soc_std(self) -> np.ndarray:
        return np.sqrt(np.maximum(self.P[:, 0, 0], 0.0))

    @property
    def params(self) -> dict[str, np.ndarray]:
        return self._params

    def _refresh_params(self, temp_c: np.ndarray) -> None:
        moved = np.abs(temp_c - self._temp_params) > self.tuning.temp_update_c
        if not moved.any():
            return
        new = ecm_parameters(self.profile, temp_c[moved])
        for key, val in new.items():
            self._params[key][moved] = val
        self._temp_params[moved] = temp_c[moved]

    def warm_start(self, history: Recording) -> None:
        """Drive the RC voltages ``U_1, U_2`` with the current recorded before the start
        (the prediction of :meth:`step`, at the recorded temperature); SOC and ``P`` stay
        as they were.  The counterpart of
        :meth:`service.estimators.pipeline.PackEstimator.warm_start`."""
        dt = history.dt_s()
        for k in range(len(history)):
            _, i, _, _, a, b = self._rc_terms(dt[k], history.current_a[k], history.temperature_c[k])
            self.x[:, 1:] = a * self.x[:, 1:] + b * i[:, None]

    def _rc_terms(self, dt_s, current_a, temp_c) -> tuple[np.ndarray, ...]:
        """``temp [N], i [N], R0 [N], R_b [N, 2], a [N, 2], b [N, 2]`` of one step:
        parameters at the temperature, the bias taken off the current, the SOC scales read
        at the prior SOC (τ unchanged) and the exact discretisation ``U_b ← a U_b + b I``."""
        n = self.n_cells
        dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (n,))
        temp = np.broadcast_to(np.asarray(temp_c, dtype=float), (n,))
        self._refresh_params(temp)
        par = self._params
        i = np.asarray(current_a, dtype=float) - par["bias"]
        r0, r_b = par["r0"], par["r"]
        if self._soc_scale is not None:
            # the profile's resistance scales over SOC, read at the prior SOC (τ unchanged)
            g_ohm, g_pol = self._soc_scale(self.x[:, 0], temp)
            r0, r_b = r0 * g_ohm, r_b * g_pol[:, None]
        # exact exponential discretisation with the actual dt
        a = np.exp(-dt[:, None] / par["tau"])  # [N, 2]
        return temp, i, r0, r_b, a, r_b * (1.0 - a)

    def _ocv_slope(self, soc: np.ndarray, temp: np.ndarray) -> np.ndarray:
        """dOCV/dSOC for the measurement Jacobian: the table's slope at ``soc``, or its secant over
        ± ``ocv_slope_span_soc`` (:class:`EkfTuning`)."""
        span = self.tuning.ocv_slope_span_soc
        if span <= 0:
            return self.ocv.slope(soc, temp)
        return (self.ocv.ocv(soc + span, temp) - self.ocv.ocv(soc - span, temp)) / (2.0 * span)

    def step(
        self,
        dt_s: np.ndarray | float,
        current_a: np.ndarray,
        voltage_v: np.ndarray,
        temp_c: np.ndarray,
    ) -> np.ndarray:
        """Predict over ``dt_s``, correct with ``voltage_v``; return the prior voltage ``[N]``."""
        n = self.n_cells
        t = self.tuning
        dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (n,))
        temp, i, r0, r_b, a, b = self._rc_terms(dt, current_a, temp_c)
        par = self._params

        # -- predict ---------------------------------------------------------------------
        g_soc = -dt / (SECONDS_PER_HOUR * par["capacity"])
        x = self.x
        x[:, 0] += g_soc * i
        x[:, 1:] = a * x[:, 1:] + b * i[:, None]
        f = np.ones((n, N_STATES))
        f[:, 1:] = a
        P = f[:, :, None] * self.P * f[:, None, :]
        g = np.concatenate([g_soc[:, None], b], axis=1)  # input column [N, 3]
        sigma_i = current_sigma_a(t.current_noise_a, t.current_noise_c, par["capacity"])
        P += (sigma_i**2)[:, None, None] * g[:, :, None] * g[:, None, :]
        q_diag = np.array(
            [t.soc_noise_per_sqrt_s**2, t.u_noise_v_per_sqrt_s**2, t.u_noise_v_per_sqrt_s**2]
        )
        P += dt[:, None, None] * np.eye(N_STATES)[None] * q_diag[None, :, None]

        # -- correct --------------------------------------------------------------------
        v_pred = self.ocv.ocv(x[:, 0], temp) - r0 * i - x[:, 1] - x[:, 2]
        if self._kinetic:
            v_pred = v_pred - kinetic_overpotential(i, par["i0"], temp)
        h = np.empty((n, N_STATES))
        h[:, 0] = self._ocv_slope(x[:, 0], temp)
        h[:, 1:] = -1.0
        ph = np.einsum("nij,nj->ni", P, h)
        r_meas = t.voltage_noise_v**2
        s = np.einsum("ni,ni->n", h, ph) + r_meas
        innovation = np.asarray(voltage_v, dtype=float) - v_pred
        if t.adaptive_noise_samples:
            # the pipeline's covariance matching (service.estimators.adaptive_noise)
            overpotential = i * (r0 + r_b.sum(axis=1))
            phi = overpotential * overpotential
            s_tot = self.noise.match(innovation, s, phi)
            r_meas = r_meas + (s_tot - s)  # the adapted extra, for the Joseph form below
            s = s_tot
        k = ph / s[:, None]
        x += k * innovation[:, None]
        ikh = np.eye(N_STATES)[None] - k[:, :, None] * h[:, None, :]
        P = np.einsum("nij,njk,nlk->nil", ikh, P, ikh) + np.reshape(r_meas, (-1, 1, 1)) * k[:, :, None] * k[:, None, :]
        self.P = 0.5 * (P + np.swapaxes(P, 1, 2))
        np.clip(x[:, 0], t.soc_clip[0], t.soc_clip[1], out=x[:, 0])
        return v_pred


class Ecm2RcEkf:
    """Estimator ``"ecm2rc-ekf"``: :class:`Ecm2RcEkfBank` run over one recording.

    Keyword arguments are the fields of :class:`EkfTuning`.
    """

    name = "ecm2rc-ekf"

    def __init__(self, **tuning: object) -> None:
        known = {f.name for f in fields(EkfTuning)}
        unknown = set(tuning) - known
        if unknown:
            raise TypeError(
                f"unknown EKF tuning option(s) {sorted(unknown)}; known: {sorted(known)}"
            )
        self.tuning = EkfTuning(**tuning)

    def run(self, recording: Recording, profile: CellProfile, soc0: float,
            history: Recording | None = None) -> EstimateTrace:
        dt = recording.dt_s()
        temp = recording.temperature_c
        bank = Ecm2RcEkfBank(profile, soc0, temp[0], n_cells=1, tuning=self.tuning)
        if history is not None:
            bank.warm_start(history)
        n = len(recording)
        soc = np.empty(n)
        std = np.empty(n)
        v_pred = np.empty(n)
        r0 = np.empty(n)
        tau = np.empty((n, 2))
        for k in range(n):
            v_pred[k] = bank.step(
                dt[k],
                recording.current_a[k : k + 1],
                recording.voltage_v[k : k + 1],
                temp[k : k + 1],
            )[0]
            soc[k] = bank.soc[0]
            std[k] = bank.soc_std[0]
            r0[k] = bank.params["r0"][0]
            tau[k] = bank.params["tau"][0]
        return EstimateTrace(
            soc=soc,
            v_pred=v_pred,
            soc_std=std,
            params={"r0_ohm": r0, "tau1_s": tau[:, 0], "tau2_s": tau[:, 1]},
        )
