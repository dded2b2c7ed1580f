"""Hu & Wang two-time-scale RLS identification and OCV-based SOC (seed 001), streaming.

Current is positive on discharge here (Hu & Wang take charge positive), so every
gain of the ARX models below is minus a resistance; resistances are reported positive.

Pipeline, one step of the uniform grid at a time (Hu & Wang Sec. III-B "cookbook"):

1. **Resampling** (ours: the paper assumes a fixed sample time ``T_s``).  Recordings
   and CAN frames come at non-uniform times, and the ARX models and Butterworth
   filters are only defined on a uniform grid, so each incoming sample is mapped onto
   a grid of period ``base_period_s`` as it arrives: the grid current is the
   charge-preserving average over the grid cell (the sample's current held over
   ``(t_{k-1}, t_k]``, project convention), the grid voltage is the voltage linearly
   interpolated at the grid time.  A long rest logged every 60 s becomes 60 grid
   points of zero current; 10 Hz data are averaged into 1 s cells.  Outputs are
   reported at each sample from the latest grid point at or before it.
2. **Fast dynamics** (Eq. 13, n = 1): current and voltage through a causal
   Butterworth high-pass (order ``hp_order``, cut-off ``hp_cutoff_hz``, streaming
   direct-form-II-transposed state), then RLS with forgetting on
   ``V_f[k] = α V_f[k-1] + β0 I[k] + β1 I[k-1]``.  In our backward-hold convention this
   is the exact discretisation of ``R0 + R1/(1 + sτ_f)``:
   ``α = e^{-T_s/τ_f}``, ``β0 = -(R0 + R1(1-α))``, ``β1 = α R0``, so
   ``R0 = β1/α``, ``R0 + R1 = -(β0+β1)/(1-α)``, ``τ_f = -T_s/ln α``.
3. **Slow dynamics** (Eqs. 11, 12, 14, m = 1): current and voltage through a causal
   Butterworth low-pass (``lp_order``, ``lp_cutoff_hz``), every ``downsample``-th grid
   value kept (``T_ss = downsample·T_s``), RLS on the form with the integrator pole
   at 1 built in: ``V_s[j] - V_s[j-2] = a1 (V_s[j-1] - V_s[j-2]) + b0 I[j] + b1 I[j-1]
   + b2 I[j-2]`` (so ``a2 = 1 - a1``, Eq. 11, and the second pole is ``λ_s = a1 - 1``).
   Its transfer function splits (partial fractions, backward hold) into
   ``c + A z/(z-1) + B z/(z-λ_s)``: static gain ``c = b2/λ_s = -(R0+R1)``, OCV integrator
   ``A = (b0+b1+b2)/(1-λ_s) = -dOCV/dSOC · T_ss/(3600 Q)``, diffusion RC
   ``B = b0 - c - A = -R2 (1-λ_s)``, ``τ_s = -T_ss/ln λ_s``.
4. **Gain consistency** (Eq. 15): the fast model's steady-state gain equals the slow
   model's static gain, ``c = G_f(1) = (β0+β1)/(1-α)``.  The text prints the
   denominator as ``1 + α1 + ...``; for the model as written in Eq. 13/16 the DC gain
   is ``Σβ/(1 - Σα)`` — a sign slip, used here corrected.  With
   ``gain_consistency=True`` the constraint is imposed on the slow fit: with
   ``b2 = (a1-1)c`` Eq. 14 stays linear, ``V_s[j]-V_s[j-2] + c I[j-2] = a1 (V_s[j-1] -
   V_s[j-2] + c I[j-2]) + b0 I[j] + b1 I[j-1]``, so RLS fits ``[a1, b0, b1]`` only.
   It is off by default: the fast model's DC gain is an extrapolation from high-passed
   data and comes out a few % off, and a small error in ``c`` moves the identified slow
   mode far from its true time constant.  The paper itself says (15)
   "will happen naturally" with well separated dynamics; its residual is reported as
   ``gain_mismatch_ohm``.
5. **SOC** (Eqs. 19-20, Fig. 7): the slow model's overvoltage (static gain and
   diffusion RC, not the integrator) is simulated on the low-pass current,
   ``V_ov = c I_filt + x``, ``x[k] = λ x[k-1] + B I_filt[k]`` (run at the grid rate with
   ``λ_s`` and ``B`` converted to ``T_s`` at the same time constant and gain, so the SOC
   is updated every grid step), ``V_oc = V_filt - V_ov`` and ``SOC = OCV⁻¹(V_oc, T)``.
   That is the paper's estimator: an OCV inverse, noisy where the OCV curve is flat,
   independent of ``soc0``.  Because ``V_filt`` is low-passed, this SOC lags the true one
   by the filter's group delay (``√2/(2π f_c)`` for the 2nd-order Butterworth: 110 s at
   2 mHz), which under a steady 1C discharge is a bias of ~3 % SOC.  Two options
   (both off by default, so the default is the paper's estimator):

   * ``lag_compensation`` — add back the charge the low-pass has not passed yet,
     ``SOC -= ∫(I - I_filt) dt / 3600 Q`` (bounded: ``I - I_filt`` has no DC part, so this
     is not coulomb counting of the mean current);
   * ``fuse_tau_s`` — coulomb counting from ``soc0`` corrected by the OCV-based SOC
     with time constant ``fuse_tau_s``: ``offset += (T_s/τ)((CC_filt - SOC_ocv) - offset)``,
     ``SOC = CC - offset``, where ``CC_filt`` is the coulomb count through the same
     low-pass (so the correction is lag-free), or the raw count when lag-compensated.
6. **Combined model** (Eq. 18) for the voltage prediction.  Eq. 18 multiplies the two
   transfer functions, which multiplies two impedances (Ω²); what the singular-
   perturbation argument means is ``G_s(z) · G_f(z)/G_f(1)``: the fast model,
   normalised to unit DC gain, shapes the current that the slow model sees.  We run
   it in that series form on the raw current, without the integrator (which drifts,
   as the paper notes) and with the OCV taken from the estimated SOC of the previous
   grid step: ``v_pred = OCV(SOC_{k-1}, T) + V_f[k] + x_c[k]``.

Eigenvalues are clipped into ``tau_fast_bounds_s`` / ``tau_slow_bounds_s`` and
resistances into ``resistance_bounds_ohm`` before they are used for simulation (an RLS
estimate can wander outside (0, 1) or to negative gains during poor excitation,
DESIGN §6); the reported parameters are the clipped values.  Initial parameters
come from the profile (``init_from_profile``) at the first temperature; the RLS
moves them from there.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy import signal

from service.cell.ocv import OcvTable
from service.cell.profile import CellProfile
from service.cell.units import SECONDS_PER_HOUR
from service.estimators.base import EstimateTrace
from service.estimators.ecm2rc_ekf import ecm_parameters
from service.estimators.rls import Rls
from service.recording import Recording

_EPS_T = 1e-9
#: the RLS problems are posed in mV and A so that the regressors of one cell are of order one
#: (low-passed voltage differences between slow samples are ~1 mV, currents ~1 A) and a
#: large initial covariance really is uninformative; gains come out in mΩ, reported in Ω.
_V_SCALE = 1e3


@dataclass(frozen=True)
class HuWangSettings:
    """Settings of the two-time-scale identifier.

    Defaults were chosen on Panasonic NCR18650PF 25 °C drive cycles (US06, LA92, Cycle2,
    NN; 1 s data), where the cell's own modes are ~4 s and ~60 s once split this way.
    The low-pass cut-off is the main trade-off: a lower cut-off identifies a slower mode
    but makes the OCV-based SOC lag by a comparable time.  A cell whose modes are further
    apart (e.g. 5 s and 500 s) wants the filters placed around its own time constants
    (Hu & Wang Fig. 3).
    """

    base_period_s: float = 1.0
    hp_cutoff_hz: float = 0.01
    hp_order: int = 2
    lp_cutoff_hz: float = 0.002
    lp_order: int = 2
    downsample: int = 20
    fast_forgetting: float = 0.9995
    slow_forgetting: float = 0.999
    fast_p0: float = 1e4
    slow_p0: float = 1e6
    max_trace: float = 1e8
    gain_consistency: bool = False
    init_from_profile: bool = True
    tau_fast_bounds_s: tuple[float, float] = (0.2, 200.0)
    tau_slow_bounds_s: tuple[float, float] = (20.0, 20000.0)
    resistance_bounds_ohm: tuple[float, float] = (0.0, 1.0)
    lag_compensation: bool = False
    fuse_tau_s: float | None = None

    def __post_init__(self) -> None:
        nyq = 0.5 / self.base_period_s
        if not 0 < self.hp_cutoff_hz < nyq:
            raise ValueError(
                f"hp_cutoff_hz must be in (0, {nyq:g}) Hz for base_period_s={self.base_period_s}"
            )
        if not 0 < self.lp_cutoff_hz < nyq / self.downsample:
            raise ValueError(
                "lp_cutoff_hz must be below the downsampled Nyquist frequency "
                f"{nyq / self.downsample:g} Hz"
            )
        if self.hp_order not in (1, 2) or self.lp_order not in (1, 2):
            raise ValueError(
                "Hu & Wang use first- or second-order Butterworth filters: order must be 1 or 2"
            )
        if self.downsample < 1:
            raise ValueError("downsample must be >= 1")


class StreamingFilter:
    """A causal IIR filter for ``N`` channels, one sample at a time (direct form II transposed).

    The state is initialised at the steady state of the first input (``lfilter_zi``),
    so a filter switched on mid-recording does not ring.
    """

    def __init__(self, b: np.ndarray, a: np.ndarray) -> None:
        self.b = np.asarray(b, dtype=float) / a[0]
        self.a = np.asarray(a, dtype=float) / a[0]
        self.z: np.ndarray | None = None

    @classmethod
    def butter(cls, order: int, cutoff_hz: float, btype: str, fs_hz: float) -> StreamingFilter:
        b, a = signal.butter(order, cutoff_hz, btype=btype, fs=fs_hz)
        return cls(b, a)

    def step(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if self.z is None:
            self.z = signal.lfilter_zi(self.b, self.a)[None, :] * x[:, None]
        z, b, a = self.z, self.b, self.a
        y = b[0] * x + z[:, 0]
        order = z.shape[1]
        for j in range(order - 1):
            z[:, j] = b[j + 1] * x + z[:, j + 1] - a[j + 1] * y
        z[:, order - 1] = b[order] * x - a[order] * y
        return y


class GridResampler:
    """Map non-uniform samples onto a uniform grid as they arrive (charge-preserving).

    :meth:`push` takes the interval since the previous sample and the new sample's
    current (held over that interval) and voltage, and returns the grid points the
    interval completed: ``[(current [N], voltage [N]), ...]``.  The first sample
    yields grid point 0.
    """

    def __init__(self, period_s: float) -> None:
        self.period = float(period_s)
        self.t = 0.0
        self.next_index = 0
        self.charge: np.ndarray | None = None
        self.v_prev: np.ndarray | None = None

    def push(
        self, dt_s: float, current_a: np.ndarray, voltage_v: np.ndarray
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        i = np.asarray(current_a, dtype=float)
        v = np.asarray(voltage_v, dtype=float)
        if self.v_prev is None:
            self.v_prev, self.charge = v.copy(), np.zeros_like(i)
            self.next_index = 1
            return [(i.copy(), v.copy())]
        out = []
        t_new = self.t + max(float(dt_s), 0.0)
        seg_start = self.t
        while self.next_index * self.period <= t_new + _EPS_T:
            g = self.next_index * self.period
            self.charge = self.charge + i * (g - seg_start)
            w = 0.0 if t_new <= self.t else (g - self.t) / (t_new - self.t)
            out.append((self.charge / self.period, self.v_prev + w * (v - self.v_prev)))
            self.charge = np.zeros_like(i)
            seg_start = g
            self.next_index += 1
        self.charge = self.charge + i * max(t_new - seg_start, 0.0)
        self.t = t_new
        self.v_prev = v.copy()
        return out


def _pole(tau_s: np.ndarray, period_s: float) -> np.ndarray:
    return np.exp(-period_s / tau_s)


def _tau(pole: np.ndarray, period_s: float, bounds: tuple[float, float]) -> np.ndarray:
    lo, hi = _pole(np.asarray(bounds[0]), period_s), _pole(np.asarray(bounds[1]), period_s)
    return -period_s / np.log(np.clip(pole, lo, hi))


class HuWangIdentifier:
    """Two-time-scale identification and OCV-based SOC for ``N`` cells sharing time stamps."""

    def __init__(
        self,
        profile: CellProfile,
        n_cells: int = 1,
        settings: HuWangSettings | None = None,
        ocv: OcvTable | None = None,
        soc0: np.ndarray | float = 0.5,
    ) -> None:
        self.profile = profile
        self.s = settings or HuWangSettings()
        self.ocv = ocv if ocv is not None else profile.ocv_table()
        self.n = int(n_cells)
        s = self.s
        fs = 1.0 / s.base_period_s
        self.hp_i = StreamingFilter.butter(s.hp_order, s.hp_cutoff_hz, "highpass", fs)
        self.hp_v = StreamingFilter.butter(s.hp_order, s.hp_cutoff_hz, "highpass", fs)
        self.lp_i = StreamingFilter.butter(s.lp_order, s.lp_cutoff_hz, "lowpass", fs)
        self.lp_v = StreamingFilter.butter(s.lp_order, s.lp_cutoff_hz, "lowpass", fs)
        self.grid = GridResampler(s.base_period_s)
        self.ts_slow = s.base_period_s * s.downsample
        self.capacity = profile.effective_capacity_ah
        self._started = False
        self._grid_count = 0
        self._fast_prev: tuple[np.ndarray, np.ndarray] | None = None  # (v_hp, i_hp) at k-1
        self._slow_hist: list[tuple[np.ndarray, np.ndarray]] = []  # (v_lp, i_lp) at j-2, j-1
        self.soc = np.full(self.n, np.nan)
        self._soc_cc = np.broadcast_to(np.asarray(soc0, dtype=float), (self.n,)).copy()
        self._cc_offset = np.zeros(self.n)  # coulomb count minus OCV-based SOC, smoothed
        self.lp_cc = StreamingFilter.butter(s.lp_order, s.lp_cutoff_hz, "lowpass", fs)
        self.v_pred = np.full(self.n, np.nan)
        self.ocv_est = np.full(self.n, np.nan)
        self.soc_ocv = np.full(self.n, np.nan)
        self._x_ov = np.zeros(self.n)  # diffusion-RC state of Eq. 19 (on I_filt)
        self._x_comb = np.zeros(self.n)  # diffusion-RC state of the combined model (Eq. 18)
        self._vf_comb = np.zeros(self.n)  # fast-model output on the raw current
        self._i_prev = np.zeros(self.n)
        self._q_unfiltered = np.zeros(
            self.n
        )  # ∫(I - I_filt) dt, charge the low-pass has not passed yet

    # -- initial guesses ----------------------------------------------------------------
    def _initial_theta(self, temp_c: np.ndarray, v0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s, ts, tss = self.s, self.s.base_period_s, self.ts_slow
        if s.init_from_profile:
            p = ecm_parameters(self.profile, temp_c)
            r0, r1, r2 = p["r0"], p["r"][:, 0], p["r"][:, 1]
            tau_f = np.clip(p["tau"][:, 0], *s.tau_fast_bounds_s)
            tau_s = np.clip(p["tau"][:, 1], *s.tau_slow_bounds_s)
        else:
            r0, r1, r2 = (np.full(self.n, 0.01) for _ in range(3))
            tau_f = np.full(self.n, np.sqrt(np.prod(s.tau_fast_bounds_s)))
            tau_s = np.full(self.n, np.sqrt(np.prod(s.tau_slow_bounds_s)))
        alpha = _pole(tau_f, ts)
        k = _V_SCALE
        theta_f = np.stack([alpha, -k * (r0 + r1 * (1 - alpha)), k * alpha * r0], axis=1)
        lam = _pole(tau_s, tss)
        c = -(r0 + r1)
        slope = self.ocv.slope(self.ocv.soc_from_ocv(v0, temp_c), temp_c)
        a_int = -slope * tss / (SECONDS_PER_HOUR * self.capacity)
        b_rc = -r2 * (1 - lam)
        b0 = c + a_int + b_rc
        b1 = -c * (1 + lam) - a_int * lam - b_rc
        if s.gain_consistency:
            theta_s = np.stack([1 + lam, k * b0, k * b1], axis=1)
        else:
            theta_s = np.stack([1 + lam, k * b0, k * b1, k * c * lam], axis=1)
        return theta_f, theta_s

    # -- derived model --------------------------------------------------------------------
    def fast_model(self) -> dict[str, np.ndarray]:
        """Fast-dynamics parameters from the Eq. 13 coefficients, clipped to physical bounds.

        The ARX coefficients used for simulation are rebuilt from the clipped
        ``(τ_f, R0, R1)`` so that the simulated model and the reported one agree.
        """
        ts = self.s.base_period_s
        r_lo, r_hi = self.s.resistance_bounds_ohm
        alpha_raw, beta0, beta1 = (
            self.rls_fast.theta.T / np.array([1.0, _V_SCALE, _V_SCALE])[:, None]
        )
        tau = _tau(alpha_raw, ts, self.s.tau_fast_bounds_s)
        alpha = _pole(tau, ts)
        r0 = np.clip(beta1 / alpha, r_lo, r_hi)
        r1 = np.clip(-(beta0 + beta1) / (1.0 - alpha) - r0, r_lo, r_hi)
        return {
            "alpha": alpha,
            "beta0": -(r0 + r1 * (1.0 - alpha)),
            "beta1": alpha * r0,
            "tau": tau,
            "r0": r0,
            "r1": r1,
            "dc_gain": -(r0 + r1),
        }  # dc_gain: corrected Eq. 15 right-hand side

    def slow_model(self, fast: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Slow-dynamics parameters from the Eq. 14 coefficients (partial fractions), clipped."""
        tss = self.ts_slow
        r_lo, r_hi = self.s.resistance_bounds_ohm
        th = self.rls_slow.theta
        a1, b0, b1 = th[:, 0], th[:, 1] / _V_SCALE, th[:, 2] / _V_SCALE
        lam_raw = a1 - 1.0
        if self.s.gain_consistency:
            c = fast["dc_gain"]
            b2 = lam_raw * c
        else:
            b2 = th[:, 3] / _V_SCALE
            c = b2 / np.where(np.abs(lam_raw) > 1e-9, lam_raw, 1e-9)
        tau = _tau(lam_raw, tss, self.s.tau_slow_bounds_s)
        lam = _pole(tau, tss)
        a_int = (b0 + b1 + b2) / (1.0 - lam)
        b_rc = b0 - c - a_int
        r2 = np.clip(-b_rc / (1.0 - lam), r_lo, r_hi)
        c_clipped = -np.clip(-c, 2 * r_lo, 2 * r_hi)
        return {
            "lam": lam,
            "tau": tau,
            "c": c_clipped,
            "a_int": a_int,
            "r2": r2,
            "docv_dsoc": -a_int * SECONDS_PER_HOUR * self.capacity / tss,
            "gain_mismatch": fast["dc_gain"] - c,
        }

    # -- streaming ------------------------------------------------------------------------
    def step(
        self, dt_s: float, current_a: np.ndarray, voltage_v: np.ndarray, temp_c: np.ndarray
    ) -> None:
        """Take one (possibly non-uniformly spaced) sample for all cells."""
        current_a = np.broadcast_to(np.asarray(current_a, dtype=float), (self.n,))
        voltage_v = np.broadcast_to(np.asarray(voltage_v, dtype=float), (self.n,))
        temp_c = np.broadcast_to(np.asarray(temp_c, dtype=float), (self.n,))
        if not self._started:
            theta_f, theta_s = self._initial_theta(temp_c, voltage_v)
            s = self.s
            self.rls_fast = Rls(theta_f, s.fast_p0, s.fast_forgetting, s.max_trace)
            self.rls_slow = Rls(theta_s, s.slow_p0, s.slow_forgetting, s.max_trace)
            self._started = True
        for i_g, v_g in self.grid.push(dt_s, current_a, voltage_v):
            self._grid_step(i_g, v_g, temp_c)

    def _grid_step(self, i: np.ndarray, v: np.ndarray, temp_c: np.ndarray) -> None:
        s = self.s
        ts = s.base_period_s
        # fast dynamics: high-pass, RLS on Eq. 13
        v_mv = v * _V_SCALE
        i_hp, v_hp = self.hp_i.step(i), self.hp_v.step(v_mv)
        if self._fast_prev is not None:
            v_hp1, i_hp1 = self._fast_prev
            self.rls_fast.update(np.stack([v_hp1, i_hp, i_hp1], axis=1), v_hp)
        self._fast_prev = (v_hp, i_hp)
        fast = self.fast_model()

        # slow dynamics: low-pass, downsample, RLS on Eq. 14 (with Eq. 15 if set)
        i_lp, v_lp = self.lp_i.step(i), self.lp_v.step(v_mv)
        if self._grid_count % s.downsample == 0:
            if len(self._slow_hist) == 2:
                (v2, i2), (v1, i1) = self._slow_hist
                if s.gain_consistency:
                    c = fast["dc_gain"] * _V_SCALE
                    y = v_lp - v2 + c * i2
                    phi = np.stack([v1 - v2 + c * i2, i_lp, i1], axis=1)
                else:
                    y = v_lp - v2
                    phi = np.stack([v1 - v2, i_lp, i1, i2], axis=1)
                self.rls_slow.update(phi, y)
            self._slow_hist = (self._slow_hist + [(v_lp, i_lp)])[-2:]
        slow = self.slow_model(fast)

        # overvoltage on the low-pass current (Eq. 19) at the grid rate, OCV (Eq. 20), SOC
        lam_b = np.power(slow["lam"], 1.0 / s.downsample)
        b_b = -slow["r2"] * (1.0 - lam_b)
        self._x_ov = lam_b * self._x_ov + b_b * i_lp
        v_ov = slow["c"] * i_lp + self._x_ov
        soc_prev = self.soc.copy()
        self.ocv_est = v_lp / _V_SCALE - v_ov
        self.soc_ocv = self.ocv.soc_from_ocv(self.ocv_est, temp_c)
        if s.lag_compensation:
            self._q_unfiltered += (i - i_lp) * ts
            self.soc_ocv = self.soc_ocv - self._q_unfiltered / (SECONDS_PER_HOUR * self.capacity)
        if s.fuse_tau_s is None:
            self.soc = self.soc_ocv
        else:
            # compare like with like: the OCV-based SOC lags by the low-pass filter unless
            # lag-compensated, so it is compared with the equally filtered coulomb count
            self._soc_cc = self._soc_cc - i * ts / (SECONDS_PER_HOUR * self.capacity)
            cc_lp = self.lp_cc.step(self._soc_cc)
            ref = self._soc_cc if s.lag_compensation else cc_lp
            k = min(ts / s.fuse_tau_s, 1.0)
            self._cc_offset += k * ((ref - self.soc_ocv) - self._cc_offset)
            self.soc = self._soc_cc - self._cc_offset

        # combined model (Eq. 18, series form G_s · G_f / G_f(1)) for the voltage prediction
        self._vf_comb = (
            fast["alpha"] * self._vf_comb + fast["beta0"] * i + fast["beta1"] * self._i_prev
        )
        self._i_prev = i
        i_eff = self._vf_comb / np.minimum(fast["dc_gain"], -1e-6)
        self._x_comb = lam_b * self._x_comb + b_b * i_eff
        soc_for_ocv = np.where(np.isnan(soc_prev), self.soc, soc_prev)
        self.v_pred = self.ocv.ocv(soc_for_ocv, temp_c) + self._vf_comb + self._x_comb
        self.fast, self.slow = fast, slow
        self._grid_count += 1

    def params(self) -> dict[str, np.ndarray]:
        """Identified parameters now (resistances positive, time constants in s)."""
        f, sl = self.fast, self.slow
        return {
            "tau_fast_s": f["tau"],
            "tau_slow_s": sl["tau"],
            "r0_ohm": f["r0"],
            "r_fast_ohm": f["r1"],
            "r_slow_ohm": sl["r2"],
            "docv_dsoc_v": sl["docv_dsoc"],
            "gain_mismatch_ohm": sl["gain_mismatch"],
            "ocv_v": self.ocv_est,
            "soc_ocv": self.soc_ocv,
        }


class HuWangRls:
    """Estimator ``"huwang-rls"``: :class:`HuWangIdentifier` run over one recording.

    Keyword arguments are the fields of :class:`HuWangSettings`.  ``soc0`` is used only
    by the ``fuse_tau_s`` option; the paper's SOC is an OCV inverse and needs none.
    """

    name = "huwang-rls"

    def __init__(self, **settings: object) -> None:
        known = {f.name for f in fields(HuWangSettings)}
        unknown = set(settings) - known
        if unknown:
            raise TypeError(f"unknown Hu-Wang option(s) {sorted(unknown)}; known: {sorted(known)}")
        self.settings = HuWangSettings(**settings)

    def run(self, recording: Recording, profile: CellProfile, soc0: float,
            history: Recording | None = None) -> EstimateTrace:
        """``history`` is ignored: the identifier's filters and RLS start from the recording
        itself, as in Hu & Wang."""
        ident = HuWangIdentifier(profile, 1, self.settings, soc0=soc0)
        dt = recording.dt_s()
        n = len(recording)
        soc = np.empty(n)
        v_pred = np.empty(n)
        params: dict[str, np.ndarray] = {}
        for k in range(n):
            ident.step(
                dt[k],
                recording.current_a[k : k + 1],
                recording.voltage_v[k : k + 1],
                recording.temperature_c[k : k + 1],
            )
            soc[k] = ident.soc[0]
            v_pred[k] = ident.v_pred[0]
            for name, val in ident.params().items():
                params.setdefault(name, np.empty(n))[k] = val[0]
        return EstimateTrace(soc=soc, v_pred=v_pred, soc_std=None, params=params)
