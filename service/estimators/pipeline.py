"""The paper's full pipeline for a whole pack: FO-MI-UKF + fast and slow identifiers (Zeng Fig. 2).

:class:`PackEstimator` is what the service drives sample by sample; the offline
estimators (``fomiukf``, ``foukf``, ``fom-single-scale``) wrap it for one cell.

Per sample: profile parameters at each cell's temperature, corrected by the
identifiers → the solid-diffusion surface deficit, if the profile carries that
extension → FO-MI-UKF prediction and update → fast identifier (EKF over
``[R_ohm, R_ct, C_dl, m, U_df]`` using the SOC filter's gain) → G-L memory push.
The slow identifier (``[R_df, C_df, n]``) buffers what it needs on the fast path and
updates in :meth:`PackEstimator.slow_update`, which the service calls once per second of
sample time and the offline runner after every sample.  With ``capacity_estimation`` on, each
cell's capacity is learned beside the SOC filter (:mod:`service.estimators.capacity`) and
fed back as the capacity the filter counts charge with; :meth:`PackEstimator.health` gives
it with its σ and the resistance growth ``R / R_nominal``.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from service.cell.fractional import gl_weights
from service.cell.memory import MAX_MEMORY_LENGTH, memory_length_at, sample_period_s
from service.cell.model import MtsFom, drive, entropic_shift_v, surface_deficit_step
from service.cell.ocv import CellOcv
from service.cell.parameters import PARAMETER_NAMES
from service.cell.profile import CellParameters, CellProfile
from service.cell.soc_dependence import scaled_resistances
from service.cell.units import SECONDS_PER_HOUR
from service.estimators.adaptive_noise import N_MOMENTS, N_SHAPE_MOMENTS
from service.estimators.base import EstimateTrace
from service.estimators.capacity import CapacityEstimator
from service.estimators.consider import MAX_REPORTED_SOC_STD, VARIANCE_ENTRIES, ConsiderCovariance
from service.estimators.fomiukf import FoMiUkf
from service.estimators.parameter_ekf import PARAMETERS, ParameterEkf, apply_corrections
from service.estimators.settings import EstimatorSettings
from service.estimators.slow_identifier import SlowIdentifier
from service.estimators.state_of_health import CellHealth
from service.recording import Recording

Identification = Literal["multi", "single", "none"]
FAST_NAMES = ["r_ohm", "r_ct", "c_dl", "m", "u_df"]
TEMP_REFRESH_C = 0.5
STATE_VERSION = 1
#: the filter keeps its SOC mean in [0, 1] (fomiukf.SOC_LIMITS); a restored SOC further out than
#: this is not a state it wrote
RESTORED_SOC_MARGIN = 0.01


class PackEstimator:
    """SOC, its σ and identified parameters for ``n_cells`` cells, advanced together."""

    def __init__(
        self,
        profile: CellProfile,
        n_cells: int,
        settings: EstimatorSettings | None = None,
        identification: Identification = "multi",
        sample_period_s: float | None = None,
    ) -> None:
        self.profile = profile
        self.settings = with_memory_for(profile, settings or EstimatorSettings(), sample_period_s)
        self.n = int(n_cells)
        self.identification = identification
        s = self.settings
        self.ocv = profile.ocv_table()
        self.n_branches = profile.n_branches
        self.ukf = FoMiUkf(self.ocv, self.n, self.n_branches, s)
        self._temp_used = np.full(self.n, 25.0)
        # the temperature extension's entropic OCV slope (V/K, reference °C), or None
        arr = profile.extensions.arrhenius
        self._entropic = (arr.entropic_v_per_k, arr.ref_temp_c) if arr is not None and arr.entropic_v_per_k else None
        self.cell_ocv = self._cell_ocv()
        self._refresh_model_error()
        #: the solid-diffusion extension (``Extensions.diffusion_surface``) or None, and its
        #: state: bulk − surface SOC per cell, a first-order lag of the measured current
        self.surface = profile.extensions.diffusion_surface
        self.surface_deficit = np.zeros(self.n)
        self.nominal = profile.parameters_at(25.0, n_cells=self.n)
        self.params = self.nominal.copy()
        self.soc_scale = profile.soc_scale_table()
        self.nominal_now = self.nominal
        nx = self.ukf.nx
        self.fast: ParameterEkf | None = None
        self.slow: SlowIdentifier | None = None
        # multi-time-scale: the fast rate identifies the fast parameters; single: all of them at once
        fast_names = {"multi": FAST_NAMES, "single": list(PARAMETER_NAMES)}.get(identification)
        if fast_names is not None and s.fast_identifier:
            self.fast = ParameterEkf(fast_names, self.n, nx, s.param_process_rel, s.voltage_noise_v,
                                     init_rel=s.param_init_std_rel, adaptive_samples=s.adaptive_noise_samples,
                                     correlation_cap=s.adaptive_noise_correlation_cap)
            self.fast.measurement = s.fast_identifier_input
        if identification == "multi" and s.slow_identifier:
            self.slow = SlowIdentifier(self.n, s.memory_length, s.slow_soc_delta, s.slow_param_process_rel)
        self.capacity: CapacityEstimator | None = None
        # a one-cell "pack" has no median cell to learn against: pack-relative is then off
        if s.capacity_estimation == "absolute" or (s.capacity_estimation == "pack-relative" and self.n >= 2):
            self.capacity = CapacityEstimator(
                self.n, profile.effective_capacity_ah, s.capacity_estimation, s.capacity_init_std_rel,
                s.capacity_bounds_rel, s.capacity_innovation_inflation, s.capacity_walk_rel_per_sqrt_s)
        #: the SOC error from what the filter does not model, for the σ published (soc_std)
        self.consider = ConsiderCovariance.from_settings(self.n, s)
        self.reset_count = np.zeros(self.n, dtype=int)
        self.ocv_initialised = np.zeros(self.n, dtype=bool)
        self.steps = 0

    @property
    def memory_length(self) -> int:
        """The G-L memory length the model runs with, in samples."""
        return self.settings.memory_length

    def set_sample_period(self, sample_period_s: float) -> None:
        """Run the model at ``sample_period_s`` from now on: the G-L memory keeps the profile's
        span (:func:`with_memory_for`).  The newest values of every memory are kept; a longer
        memory is padded with zeros (relaxed) beyond what was held."""
        self.resize_memory(with_memory_for(self.profile, self.settings, sample_period_s).memory_length)

    def resize_memory(self, memory_length: int) -> None:
        """Hold ``memory_length`` samples of G-L memory (the filter's and the slow identifier's)."""
        length = int(memory_length)
        if length == self.memory_length:
            return
        self.settings = self.settings.model_copy(update={"memory_length": length})
        self.ukf.resize_memory(length)
        if self.slow is not None:
            self.slow.resize_memory(length)

    # -- parameters ---------------------------------------------------------------------
    def _entropic_shift(self, temp_c: np.ndarray) -> np.ndarray | None:
        """``dOCV/dT · (T - T_ref)`` of the temperature extension (None without one)."""
        if self._entropic is None:
            return None
        return entropic_shift_v(*self._entropic, temp_c)

    def _cell_ocv(self) -> CellOcv:
        return CellOcv(self.ocv, self._temp_used, self._entropic_shift(self._temp_used))

    def _refresh_nominal(self, temp_c: np.ndarray, force: bool = False) -> None:
        moved = ~(np.abs(temp_c - self._temp_used) < TEMP_REFRESH_C) | force
        if moved.any():
            self.nominal = self.profile.parameters_at(np.where(moved, temp_c, self._temp_used))
            self._temp_used = np.where(moved, temp_c, self._temp_used)
            self.cell_ocv = self._cell_ocv()
            self._refresh_model_error()

    def _refresh_model_error(self) -> None:
        """The SOC filter's model error per C-rate at each cell's temperature, from the profile's
        fit RMSE there (``voltage_noise_per_fit_rmse``; unset: the settings' constant)."""
        k = self.settings.voltage_noise_per_fit_rmse
        ecm = self.profile.ecm2rc
        rmse = ecm.fit_rmse_v_at(self._temp_used) if k > 0 and ecm is not None else None
        self.ukf.model_error_per_c_v = None if rmse is None else k * rmse

    def _surface_step(self, dt_s: float, current_a: np.ndarray, params: CellParameters) -> None:
        """Advance bulk − surface SOC ``x`` as the model does (:func:`service.cell.model.surface_deficit_step`).
        ``x`` depends on the current alone, so it is propagated beside the filter rather than
        as a filter state."""
        if self.surface is None:
            return
        self.surface_deficit = surface_deficit_step(self.surface_deficit, current_a - params.current_bias_a, dt_s,
                                                    self.surface.tau_s, self.surface.gain, params.capacity_ah)

    def _soc_nominal(self) -> CellParameters:
        """The nominal parameters at each cell's present SOC estimate (resistance scales of
        :mod:`service.cell.soc_dependence`; the nominal itself when the profile has none).
        The identifiers correct this scaled nominal, so their corrections stay relative."""
        if self.soc_scale is None:
            return self.nominal
        nom = self.nominal
        g_ohm, g_pol = self.soc_scale(self.ukf.soc, self._temp_used)
        r_ohm, r, c = scaled_resistances(nom.r_ohm, nom.r, nom.c, g_ohm, g_pol)
        return dataclasses.replace(nom, r_ohm=r_ohm, r=r, c=c)

    def _current_params(self) -> CellParameters:
        p = self.params
        nom = self._soc_nominal()
        self.nominal_now = nom
        p.r_ohm, p.r[:], p.c[:], p.alpha[:] = nom.r_ohm, nom.r, nom.c, nom.alpha
        for k in ("u_h_max", "hyst_rate", "capacity_ah", "current_bias_a", "kinetics_i0_a"):
            setattr(p, k, getattr(nom, k))
        if self.fast is not None:
            apply_corrections(nom, self.fast.names, self.fast.z, p)
        if self.slow is not None:
            apply_corrections(nom, list(PARAMETERS)[4:7], self.slow.z, p)
        if self.capacity is not None:
            p.capacity_ah = nom.capacity_ah / self.capacity.state.phi
        return p

    def parameters(self) -> dict[str, np.ndarray]:
        """Identified parameters now: r_ohm, r_ct, c_dl, m, r_df, c_df, n (+ u_df)."""
        p = self.params
        out = {
            "r_ohm": p.r_ohm.copy(),
            "r_ct": p.r[:, 0].copy(),
            "c_dl": p.c[:, 0].copy(),
            "m": p.alpha[:, 0].copy(),
            "r_df": p.r[:, 1].copy(),
            "c_df": p.c[:, 1].copy(),
            "n": p.alpha[:, 1].copy(),
        }
        if self.fast is not None and self.fast.u_df is not None:
            out["u_df"] = self.fast.u_df.copy()
        return out

    @property
    def capacity_ah(self) -> np.ndarray:
        """Each cell's capacity as the SOC filter uses it: the online estimate, or the profile's
        when capacity estimation is off."""
        if self.capacity is not None:
            return self.capacity.capacity_ah.copy()
        return np.full(self.n, float(self.profile.effective_capacity_ah))

    def health(self) -> CellHealth:
        """State of health per cell: the capacity and its σ (the profile's with σ 0 when the
        estimate is frozen), capacity / profile's, and the SOH-power figure
        ``(R_ohm + R_ct) / (R_ohm + R_ct)_nominal``.

        The identified resistances are corrections of the profile's at the cell's own
        temperature (Arrhenius table) and SOC (:mod:`service.cell.soc_dependence`), so their
        ratio to that nominal is the resistance normalised to the profile's reference
        conditions: a cell at 10 °C with the profile's resistance there reads 1.0."""
        nominal = self.profile.effective_capacity_ah
        cap = self.capacity_ah
        cap_std = self.capacity.capacity_std_ah if self.capacity is not None else np.zeros(self.n)
        p, nom = self.params, self.nominal_now
        r = p.r_ohm + p.r[:, 0]
        r_nom = nom.r_ohm + nom.r[:, 0]
        return CellHealth(capacity_ah=cap, capacity_std_ah=cap_std, capacity_rel=cap / nominal,
                          resistance_rel=r / r_nom)

    # -- initialisation -----------------------------------------------------------------
    def initialise(
        self,
        voltage_v: np.ndarray,
        temperature_c: np.ndarray,
        current_a: float | np.ndarray = 0.0,
        cells: np.ndarray | None = None,
    ) -> None:
        """OCV-based start: SOC from the voltage (IR-corrected), σ = ``soc_init_std``."""
        cells = np.ones(self.n, dtype=bool) if cells is None else np.asarray(cells, dtype=bool)
        temp = np.broadcast_to(np.asarray(temperature_c, float), (self.n,))
        self._refresh_nominal(temp, force=not self.steps)
        i = np.broadcast_to(np.asarray(current_a, float), (self.n,))
        v = np.broadcast_to(np.asarray(voltage_v, float), (self.n,)) + self.nominal.r_ohm * i
        shift = self._entropic_shift(temp)
        if shift is not None:
            v = v - shift
        # a (re)start relaxes the surface deficit with the branches, so surface SOC = SOC here
        soc = np.clip(self.ocv.soc_from_ocv(v, temp), 0.0, 1.0)
        self.start(soc, cells=cells)
        self.ocv_initialised[cells] = True

    def start(self, soc: np.ndarray | float, cells: np.ndarray | None = None, soc_std: float | None = None) -> None:
        """Start ``cells`` at a given SOC (used by evaluation: a deliberately wrong start)."""
        cells = np.ones(self.n, dtype=bool) if cells is None else np.asarray(cells, dtype=bool)
        soc_arr = np.broadcast_to(np.asarray(soc, float), (self.n,))
        std = self.settings.soc_init_std if soc_std is None else soc_std
        capacity = self.profile.effective_capacity_ah
        bias_std = self.settings.current_bias_init_std_c * capacity
        self.ukf.reset(cells, soc_arr[cells], std, float(self.profile.hysteresis.u_h_max_v), bias_std)
        self.surface_deficit[cells] = 0.0
        if self.fast is not None:
            self.fast.reset(cells)
        if self.capacity is not None:
            self.capacity.restart(cells)
        self.consider.restart(cells)
        self.ocv_initialised[cells] = False

    def widen_soc_std(self, extra_std: float | np.ndarray, max_std: float = 0.5) -> None:
        """Add ``extra_std`` (SOC fraction) in quadrature to every cell's SOC σ, capped at ``max_std``.

        For a state known to be old (a restart after downtime): the pack may have moved by
        that much since, so the filter must trust its next voltages more than this state.
        """
        ukf = self.ukf
        i = ukf.i_soc
        extra = np.broadcast_to(np.asarray(extra_std, float), (self.n,))
        var = np.minimum(ukf.P[:, i, i] + extra**2, max_std**2)
        ukf.P[:, i, i] = np.maximum(var, ukf.P[:, i, i])

    def widen_for_downtime(self, age_s: float, c_rate: float, max_soc_std: float = 0.5) -> float:
        """Widen a restored state that is ``age_s`` old; returns the SOC σ added (fraction).

        While the service was down the pack may have carried up to ``c_rate`` × 1 C, so the
        SOC may have moved by ``c_rate`` × ``age_s`` / 3600 (added in quadrature, see
        :meth:`widen_soc_std`), and every polarisation branch (Zeng Eq. 3) may hold anything
        up to the voltage it settles to at that current, R_k × I: each branch's σ is raised
        to at least that.  Without the branch widening the filter explains the stale branch
        voltages with SOC, and its SOC σ collapses while the error stays."""
        moved = float(c_rate) * max(float(age_s), 0.0) / SECONDS_PER_HOUR
        self.widen_soc_std(moved, max_soc_std)
        current = float(c_rate) * self.profile.effective_capacity_ah
        P = self.ukf.P
        for k in range(self.n_branches):
            P[:, k, k] = np.maximum(P[:, k, k], (self.params.r[:, k] * current) ** 2)
        return moved

    def warm_start(self, history: Recording, cells: np.ndarray | None = None) -> None:
        """Drive ``cells``' polarisation states with the current recorded before the start.

        The cell model (Zeng Eqs. 1, 3, 5: every CPE or extra branch with its G-L memory,
        and the hysteresis voltage ``U_h``) is simulated along ``history`` with the
        profile's parameters at the recorded temperature; the filter's branch means,
        G-L memory and ``U_h`` mean are set to the model's state at the end.  These
        states depend on the current alone, so the SOC (and every covariance) stays as
        :meth:`start` set it.  This is what a service that had been running through
        ``history`` would know; without it a branch of time constant τ starts relaxed,
        which is wrong for about τ after the last load (an hour-long slow branch after
        a ten-minute rest)."""
        cells = np.ones(self.n, dtype=bool) if cells is None else np.asarray(cells, dtype=bool)
        if len(history) == 0 or not cells.any():
            return
        params = self.profile.parameters_at(np.full(self.n, history.temperature_c[0]))
        # SOC matters only to resistance scales over SOC: count back from the start SOC
        charge_ah = float(np.sum(history.current_a * history.dt_s())) / SECONDS_PER_HOUR
        model = MtsFom(self.profile, params, self.ukf.soc + charge_ah / params.capacity_ah, self.settings.memory_length)
        drive(model, history.time_s, history.current_a, history.temperature_c)
        b = self.n_branches
        self.ukf.hist[cells] = model.history[cells]
        self.ukf.x[cells, :b] = model.history[cells, :, 0]
        self.ukf.x[cells, self.ukf.i_uh] = model.u_h[cells]
        self.surface_deficit[cells] = model.x_surf[cells]

    # -- the fast path ------------------------------------------------------------------
    def step(
        self,
        dt_s: float,
        current_a: float | np.ndarray,
        voltage_v: np.ndarray,
        temperature_c: np.ndarray,
        active: np.ndarray | None = None,
    ) -> None:
        """Advance every cell by one sample.  Inactive (stale) cells integrate the pack
        current in the prediction but take no voltage update; their σ grows."""
        n = self.n
        i = np.broadcast_to(np.asarray(current_a, float), (n,)).copy()
        v = np.asarray(voltage_v, float)
        temp = np.broadcast_to(np.asarray(temperature_c, float), (n,))
        act = np.ones(n, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        act = act & np.isfinite(v)
        v = np.where(act, v, 0.0)
        dt = float(dt_s)
        self._refresh_nominal(np.where(np.isfinite(temp), temp, self._temp_used))
        params = self._current_params()
        weights = gl_weights(params.alpha, self.settings.memory_length)
        ukf = self.ukf
        self._surface_step(dt, i, params)
        surface = self.surface_deficit if self.surface is not None else None
        ukf.predict(dt, i, params, weights)
        if self.capacity is not None:  # the capacity's uncertainty as SOC process noise
            ukf.P[:, ukf.i_soc, ukf.i_soc] += self.capacity.soc_process_var(i - params.current_bias_a, dt)
        ukf.update(v, i, temp, params, act, self.cell_ocv, surface)
        if self.capacity is not None:
            soc_now = self.surface_soc()
            usable = act & (ukf.soc_std < self.settings.identify_below_soc_std)
            shift = self.capacity.update(i - params.current_bias_a, dt, ukf.innovation, ukf.innovation_var,
                                         self.cell_ocv.slope(soc_now), ukf.gain[:, ukf.i_soc], usable,
                                         ukf.innovation_var_own)
            ukf.x[:, ukf.i_soc] = np.clip(ukf.x[:, ukf.i_soc] + shift, 0.0, 1.0)
        self.consider.step(dt, *self.consider_inputs(act))
        if self.fast is not None:
            x_id = ukf.x_single if self.settings.identifier_sees == "single" else ukf.x
            soc_post = x_id[:, ukf.i_soc]
            if surface is not None:
                soc_post = soc_post - surface  # the OCV is read at the particle surface
            identify = act & (ukf.soc_std < self.settings.identify_below_soc_std)
            ocv_post, slope_post = self.cell_ocv.ocv_and_slope(soc_post)
            if ukf.i_ocv is not None:  # the output's OCV includes the table-error state
                ocv_post = ocv_post + x_id[:, ukf.i_ocv]
            self.fast.update(
                nominal=self.nominal_now,
                params=params,
                weights=weights,
                hist=ukf.hist,
                x_post=x_id,
                soc_slope=slope_post,
                ocv_post=ocv_post,
                gain=ukf.gain,
                transition=ukf.transition,
                current_a=i,
                dt_s=dt,
                voltage_v=v,
                active=identify,
                kinetic_v=ukf.kinetic_v,
            )
        ukf.push_history()
        if self.slow is not None:
            u_df = self.fast.u_df if self.fast is not None and self.fast.u_df is not None else ukf.x[:, 1]
            self.slow.record(dt, i - params.current_bias_a, u_df, params.capacity_ah)
        bad = ukf.diverged()
        if bad.any():
            self.reset_count[bad] += 1
            self.initialise(np.where(act, v, self.v_pred), temp, i, cells=bad & act)
            still = bad & ~act
            if still.any():
                self.start(np.clip(np.nan_to_num(ukf.soc, nan=0.5), 0, 1), cells=still)
        self.steps += 1

    def slow_update(self) -> np.ndarray:
        """Run the slow identifier if SOC has moved enough; returns which cells updated."""
        if self.slow is None:
            return np.zeros(self.n, dtype=bool)
        nom = self.nominal_now
        converged = self.ukf.soc_std < self.settings.identify_below_soc_std
        return self.slow.update(nom.r[:, 1], nom.c[:, 1], nom.alpha[:, 1], cells=converged)

    # -- outputs ------------------------------------------------------------------------
    @property
    def soc(self) -> np.ndarray:
        return self.ukf.soc

    def surface_soc(self) -> np.ndarray:
        """The SOC filter's SOC at the particle surface, where the OCV is read (bulk SOC without the
        solid-diffusion extension)."""
        return self.ukf.soc if self.surface is None else self.ukf.soc - self.surface_deficit

    def consider_inputs(self, active: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """SOC, the SOC gain of this sample's update (0 where a cell took no voltage) and the OCV
        slope there: what :meth:`ConsiderCovariance.step` propagates the unmodelled errors with."""
        ukf = self.ukf
        gain = np.where(active, ukf.gain[:, ukf.i_soc], 0.0)
        return ukf.soc, gain, self.cell_ocv.slope(self.surface_soc())

    @property
    def soc_std(self) -> np.ndarray:
        """The SOC σ published: the filter's own and what the errors it does not model add
        (:mod:`service.estimators.consider`)."""
        return np.minimum(np.sqrt(self.ukf.soc_std**2 + self.consider.soc_var), MAX_REPORTED_SOC_STD)

    @property
    def filter_soc_std(self) -> np.ndarray:
        """The SOC filter's own σ, which gates the identifiers and the service's convergence flags."""
        return self.ukf.soc_std

    @property
    def v_pred(self) -> np.ndarray:
        return self.ukf.v_pred

    # -- persistence --------------------------------------------------------------------
    def get_state(self) -> dict[str, np.ndarray]:
        """Complete state (SOC, covariance, parameters, fractional memory) as arrays."""
        u = self.ukf
        st: dict[str, np.ndarray] = {
            "state_version": np.array(STATE_VERSION),
            "n_cells": np.array(self.n),
            "memory_length": np.array(self.settings.memory_length),
            "ukf_x": u.x, "ukf_P": u.P, "ukf_hist": u.hist, "ukf_var_hist": u.var_hist,
            "ukf_innovations": u.innovations, "ukf_gains": u.gains, "ukf_nis": u.nis_ema,
            "ukf_noise_moments": u.noise.moments, "ukf_noise_previous": u.noise.previous,
            "reset_count": self.reset_count, "ocv_initialised": self.ocv_initialised,
            "surface_deficit": self.surface_deficit,
        }
        if self.fast is not None:
            st.update(fast_z=self.fast.z, fast_P=self.fast.P, fast_D=self.fast.D)
            if self.fast.noise is not None:
                st.update(fast_noise_moments=self.fast.noise.moments, fast_noise_previous=self.fast.noise.previous)
            st.update(self.fast.difference_state(self.n))
        if self.slow is not None:
            st.update(slow_z=self.slow.z, slow_P=self.slow.P, slow_ring=self.slow.ring, slow_moved=self.slow.moved)
        if self.capacity is not None:
            st.update(self.capacity.get_state())
        st.update(self.consider.get_state())
        return {k: np.array(v, copy=True) for k, v in st.items()}

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore :meth:`get_state` output; raises ``ValueError`` if it does not fit."""
        def need(key: str, shape: tuple[int, ...]) -> np.ndarray:
            if key not in state:
                raise ValueError(f"estimator state lacks '{key}'")
            arr = np.asarray(state[key])
            if arr.shape != shape:
                raise ValueError(f"estimator state '{key}' has shape {arr.shape}, expected {shape}")
            if arr.dtype.kind not in "biuf":  # text or complex numbers: not a state this filter wrote
                raise ValueError(f"estimator state '{key}' is not real numbers ({arr.dtype})")
            if arr.dtype.kind == "f" and not np.isfinite(arr).all():
                raise ValueError(f"estimator state '{key}' holds non-finite values")
            return arr.copy()

        def noise_state(prefix: str) -> tuple[np.ndarray, np.ndarray | None]:
            # states written before the innovation's autocorrelation was kept: the shape moments alone
            key = f"{prefix}_noise_moments"
            width = N_SHAPE_MOMENTS if np.shape(state[key])[1:] == (N_SHAPE_MOMENTS,) else N_MOMENTS
            moments = need(key, (self.n, width))
            previous = need(f"{prefix}_noise_previous", (self.n,)) if f"{prefix}_noise_previous" in state else None
            return moments, previous

        u = self.ukf
        if int(np.asarray(state.get("state_version", -1))) != STATE_VERSION:
            raise ValueError("estimator state has another version")
        # the memory the state was saved with (a service that measured its sample period resized it)
        length = int(np.asarray(state.get("memory_length", self.memory_length)))
        if not 1 <= length <= MAX_MEMORY_LENGTH:
            raise ValueError(f"estimator state's memory_length {length} is outside 1..{MAX_MEMORY_LENGTH}")
        x = need("ukf_x", u.x.shape)
        P = need("ukf_P", u.P.shape)
        # a state this filter wrote keeps SOC near [0, 1] and a covariance with a non-negative diagonal
        soc = x[:, u.i_soc]
        if np.any((soc < -RESTORED_SOC_MARGIN) | (soc > 1.0 + RESTORED_SOC_MARGIN)):
            raise ValueError(f"estimator state's SOC reaches {soc.min():.3g}..{soc.max():.3g}, outside [0, 1]")
        if np.any(np.diagonal(P, axis1=-2, axis2=-1) < 0):
            raise ValueError("estimator state's covariance has a negative variance")
        hist = need("ukf_hist", u.hist.shape[:-1] + (length,))
        var_hist = need("ukf_var_hist", u.var_hist.shape[:-1] + (length,))
        innov = need("ukf_innovations", u.innovations.shape)
        gains = need("ukf_gains", u.gains.shape)
        nis = need("ukf_nis", u.nis_ema.shape)
        # adaptive noise: moments; older states kept one variance per cell, or none (starts from zero)
        if "ukf_noise_moments" in state:
            noise_moments, noise_previous = noise_state("ukf")
        else:
            noise_previous = None
            legacy = need("ukf_r_adapt", (self.n,)) if "ukf_r_adapt" in state else np.zeros(self.n)
            noise_moments = np.zeros_like(u.noise.moments)
            noise_moments[:, 3] = legacy
        fast = slow = None
        if self.fast is not None:
            fast = (need("fast_z", self.fast.z.shape), need("fast_P", self.fast.P.shape), need("fast_D", self.fast.D.shape))
            # the 'difference' input's previous sample (states written before it existed: none)
            prev = ((need("fast_prev_v", (self.n,)), need("fast_prev_h", (self.n,)),
                     need("fast_prev_c", self.fast.D.shape[:1] + self.fast.D.shape[2:]),
                     need("fast_prev_active", (self.n,)))
                    if "fast_prev_v" in state else None)
            # the identifier's matched noise (states written before it existed, or without it: none learned)
            fast_noise = (noise_state("fast")
                          if self.fast.noise is not None and "fast_noise_moments" in state else None)
        if self.slow is not None:
            slow = (need("slow_z", self.slow.z.shape), need("slow_P", self.slow.P.shape),
                    need("slow_ring", self.slow.ring.shape[:-1] + (length,)), need("slow_moved", self.slow.moved.shape))
        # the capacity estimate (states written before it existed, or while frozen: the profile's)
        capacity = None
        if self.capacity is not None and all(k in state for k in CapacityEstimator.STATE_KEYS):
            capacity = tuple(need(k, (self.n,)) for k in CapacityEstimator.STATE_KEYS)
        # the considered errors' covariance (states written before it existed: the priors, c = 0)
        consider = ((need("consider_entries", self.consider.entries.shape), need("consider_last_soc", (self.n,)))
                    if "consider_entries" in state else None)
        if consider is not None and np.any(consider[0][list(VARIANCE_ENTRIES)] < 0):
            raise ValueError("estimator state's considered covariance has a negative variance")
        resets = need("reset_count", self.reset_count.shape).astype(int)
        if np.any(resets < 0):
            raise ValueError("estimator state's reset_count is negative")
        ocv_init = need("ocv_initialised", self.ocv_initialised.shape).astype(bool)
        # states written before the surface deficit was kept: a relaxed surface
        surface = need("surface_deficit", (self.n,)) if "surface_deficit" in state else np.zeros(self.n)
        self.resize_memory(length)
        u.x, u.P, u.hist, u.var_hist, u.innovations, u.gains, u.nis_ema = x, P, hist, var_hist, innov, gains, nis
        u.noise.set_moments(noise_moments, noise_previous)
        self.reset_count, self.ocv_initialised = resets, ocv_init
        self.surface_deficit = surface
        if fast is not None:
            self.fast.z, self.fast.P, self.fast.D = fast
            self.fast.set_difference_state(prev)
            if fast_noise is not None:
                self.fast.noise.set_moments(*fast_noise)
            elif self.fast.noise is not None:
                self.fast.noise.reset(np.arange(self.n))
        if slow is not None:
            self.slow.z, self.slow.P, self.slow.ring, self.slow.moved = slow
            self.slow.hist0 = self.slow.ring.copy()
            self.slow.length = 0
            self.slow.start[:] = 0
        if capacity is not None:
            self.capacity.set_state(capacity)
        if consider is not None:
            self.consider.set_state(*consider)
        else:
            self.consider.restart(np.ones(self.n, dtype=bool))


def with_memory_for(profile: CellProfile, settings: EstimatorSettings,
                    sample_period_s: float | None) -> EstimatorSettings:
    """``settings`` with the G-L memory length that keeps ``profile.memory_span_s`` at
    ``sample_period_s`` (:mod:`service.cell.memory`); unchanged without a span or a period, or
    with ``memory_follows_sample_period`` off."""
    if not settings.memory_follows_sample_period:
        return settings
    length = memory_length_at(profile.memory_span_s, sample_period_s, settings.memory_length)
    return settings if length == settings.memory_length else settings.model_copy(update={"memory_length": length})


# -- offline estimators (one cell, for ``socd evaluate``) ---------------------------------
class PipelineEstimator:
    """Runs :class:`PackEstimator` for one cell along a recording."""

    def __init__(self, name: str, identification: Identification, settings: EstimatorSettings | None = None,
                 **overrides: object) -> None:
        self.name = name
        self.identification = identification
        base = settings or EstimatorSettings()
        self.settings = base.model_copy(update=overrides) if overrides else base

    def run(self, recording: Recording, profile: CellProfile, soc0: float,
            history: Recording | None = None) -> EstimateTrace:
        est = PackEstimator(profile, 1, self.settings, self.identification, sample_period_s(recording.time_s))
        est.start(np.array([soc0]))
        if history is not None:
            est.warm_start(history)
        T = len(recording)
        soc = np.empty(T)
        std = np.empty(T)
        own_std = np.empty(T)
        vp = np.empty(T)
        params = {k: np.empty(T) for k in PARAMETER_NAMES}
        bias = np.empty(T) if self.settings.current_bias_state else None
        dt = recording.dt_s()
        one = np.ones(1, dtype=bool)
        for k in range(T):
            est.step(dt[k], recording.current_a[k], recording.voltage_v[k:k + 1], recording.temperature_c[k:k + 1], one)
            est.slow_update()
            soc[k], std[k], own_std[k], vp[k] = est.soc[0], est.soc_std[0], est.filter_soc_std[0], est.v_pred[0]
            p = est.params
            params["r_ohm"][k], params["r_ct"][k], params["c_dl"][k], params["m"][k] = p.r_ohm[0], p.r[0, 0], p.c[0, 0], p.alpha[0, 0]
            params["r_df"][k], params["c_df"][k], params["n"][k] = p.r[0, 1], p.c[0, 1], p.alpha[0, 1]
            if bias is not None:
                bias[k] = est.ukf.current_bias_a[0]
        if bias is not None:
            params["current_bias_a"] = bias
        return EstimateTrace(soc=soc, v_pred=vp, soc_std=std, filter_soc_std=own_std, params=params)


#: innovation window of the paper's FO-MI-UKF when the settings ask for a single innovation
PAPER_INNOVATION_LENGTH = 4


def fomiukf(settings: EstimatorSettings | None = None) -> PipelineEstimator:
    """The paper's full pipeline: FO-MI-UKF (window ``PAPER_INNOVATION_LENGTH`` unless the
    settings give a longer one) + multi-time-scale identification."""
    base = settings or EstimatorSettings()
    return PipelineEstimator("fomiukf", "multi", base, innovation_length=max(base.innovation_length, PAPER_INNOVATION_LENGTH))


def foukf(settings: EstimatorSettings | None = None) -> PipelineEstimator:
    """Single-innovation FO-UKF: the same code with the innovation window set to 1."""
    return PipelineEstimator("foukf", "multi", settings, innovation_length=1)


def fom_single_scale(settings: EstimatorSettings | None = None) -> PipelineEstimator:
    """Single-time-scale identification: one EKF over all seven parameters at the sample rate
    (with the paper's multi-innovation window, so it differs from ``fomiukf`` only there)."""
    base = settings or EstimatorSettings()
    return PipelineEstimator("fom-single-scale", "single", base, innovation_length=max(base.innovation_length, PAPER_INNOVATION_LENGTH))
