"""Fractional-order multi-innovation unscented Kalman filter (Zeng §3.1, Table 3), per pack.

State per cell ``x = [U_1..U_B, SOC, U_h]`` (branch 0 = U_cd, branch 1 = U_df).  The
prediction carries the G-L memory: each branch is advanced with the implicit step of
:mod:`service.cell.fractional`, the memory sum ``Σ_{j≥2} w_j U_{k-j}`` is taken over
the *posterior means* of past steps (Table 3 step 4), and the covariance gets the
memory term ``Σ_{j≥2} (w_j/d)^2 P_{k-j}`` on the branch diagonals (step 5).

Update (Table 3 steps 6-8, Zeng Eqs. 18-20): innovations and gains of the last ``p``
samples are kept; ``x+ = x- + Σ_i γ_i K_{k-i+1} e_{k-i+1}`` with ``γ_i`` the
fractional coefficients ``|w_{i-1}(n)|`` of the diffusion order.  With
``innovation_weighting='normalized'`` the ``γ`` are scaled to sum to one, so the
information in old innovations is not added a second time; ``'paper'`` keeps Eq. 20
as printed.  The covariance update subtracts (Table 3 step 8 prints ``+``):
``P+ = P- - K Pyy Kᵀ``, using the current gain only.  The single-innovation posterior
``x- + K e`` is kept as ``x_single`` for the fast identifier (see
``EstimatorSettings.identifier_sees``).

With ``current_bias_state`` the state gains a last element ``b``, the current sensor's offset
in A (not in the paper): SOC integrates ``I - b`` (Zeng Eq. 4 with the measured current
corrected), ``b`` is a slow random walk, and the update learns it through its covariance with
SOC, i.e. from a drift of SOC against the OCV.  The offset enters only the integral: its
instantaneous effect on the branch and ohmic drops (tens of mA times tens of mΩ) is below
the voltage noise and is left out, so the output does not depend on ``b`` directly.

With ``ocv_error_std_v > 0`` the state gains a last element ``e_ocv``, the OCV table's error at
the present SOC (not in the paper): the output is ``OCV(SOC) + e_ocv + ...``, and ``e_ocv`` is a
first-order Gauss-Markov process in SOC, ``e_ocv ← ρ e_ocv + w``, ``ρ = exp(-|ΔSOC| / L)``,
``var(w) = σ² (1 - ρ²)``, stationary at σ.  A table error is a bias, the same at every sample
taken at one SOC; as white measurement noise, a long rest's samples would each count as new
evidence and pull SOC onto the table's error.  Held at rest (ρ = 1), the state takes up a
residual that persists there, and it decorrelates as the SOC moves.
"""

from __future__ import annotations

import numpy as np

from service.cell.fractional import gl_weights, resized_history
from service.cell.hysteresis import hysteresis_decay
from service.cell.model import kinetic_overpotential
from service.cell.ocv import CellOcv, OcvTable
from service.cell.profile import CellParameters
from service.cell.units import SECONDS_PER_HOUR
from service.estimators.adaptive_noise import AdaptiveNoise
from service.estimators.settings import EstimatorSettings
from service.estimators.sigma_points import merwe_weights, robust_cholesky, sigma_points

#: the filter's SOC mean stays in [0, 1] (DESIGN: SOC in [0, 1] internally): a cell holds
#: neither more than full nor less than empty; sigma points may still spread beyond it
SOC_LIMITS = (0.0, 1.0)


class FoMiUkf:
    """SOC filter for ``n_cells`` cells with ``n_branches`` CPE branches."""

    def __init__(self, ocv: OcvTable, n_cells: int, n_branches: int, settings: EstimatorSettings) -> None:
        self.ocv = ocv
        self.settings = settings
        self.n = n_cells
        self.b = n_branches
        self.nx = n_branches + 2 + int(settings.current_bias_state) + int(settings.ocv_error_std_v > 0)
        self.i_soc = n_branches
        self.i_uh = n_branches + 1
        #: index of the current-offset state (None without ``current_bias_state``)
        self.i_bias: int | None = n_branches + 2 if settings.current_bias_state else None
        #: index of the OCV-table error state (None without ``ocv_error_std_v``)
        self.i_ocv: int | None = self.nx - 1 if settings.ocv_error_std_v > 0 else None
        L = settings.memory_length
        p = settings.innovation_length
        self.x = np.zeros((n_cells, self.nx))
        self.P = np.tile(np.eye(self.nx) * 1e-4, (n_cells, 1, 1))
        self.hist = np.zeros((n_cells, n_branches, L))
        self.var_hist = np.zeros((n_cells, n_branches, L))
        self.innovations = np.zeros((n_cells, p))
        self.gains = np.zeros((n_cells, p, self.nx))
        self.wm, self.wc, self.gamma = merwe_weights(self.nx, settings.ukf_alpha, settings.ukf_beta, settings.ukf_kappa)
        self.nis_ema = np.ones(n_cells)
        #: adaptive measurement variance (covariance matching); inert unless adaptive_noise_samples
        self.noise = AdaptiveNoise(n_cells, max(settings.adaptive_noise_samples, 1), settings.adaptive_noise_shape,
                                   settings.adaptive_noise_correlation_cap)
        self.repairs = 0
        # outputs of the last step, used by the identifiers
        self.gain = np.zeros((n_cells, self.nx))
        self.transition = np.ones((n_cells, self.nx))
        self.innovation = np.zeros(n_cells)
        self.innovation_var = np.ones(n_cells)
        self.innovation_var_own = np.ones(n_cells)
        self.v_pred = np.zeros(n_cells)
        self.kinetic_v: np.ndarray | None = None
        #: per-cell model error per C-rate (V) set by the pipeline from the profile's fit RMSE at each
        #: cell's temperature (``voltage_noise_per_fit_rmse``); None: the settings' constant
        self.model_error_per_c_v: np.ndarray | None = None
        #: this sample's single-innovation posterior ``x- + K e`` (the multi-innovation one is ``x``):
        #: what the fast identifier's Table-1 sensitivity assumes the filter did with this sample
        self.x_single = self.x

    # -- initialisation -----------------------------------------------------------------
    def resize_memory(self, length: int) -> None:
        """Hold ``length`` samples of G-L memory, the newest kept (:func:`service.cell.fractional.resized_history`)."""
        self.hist = resized_history(self.hist, length)
        self.var_hist = resized_history(self.var_hist, length)

    def reset(
        self, cells: np.ndarray, soc: np.ndarray, soc_std: float, u_h_std: float, bias_std_a: float = 0.0
    ) -> None:
        """(Re)start ``cells`` (bool mask) at ``soc`` with relaxed branches (and a zero
        current offset of σ ``bias_std_a`` when the filter has that state)."""
        self.x[cells] = 0.0
        self.x[cells, self.i_soc] = soc
        self.hist[cells] = 0.0
        self.var_hist[cells] = 0.0
        self.innovations[cells] = 0.0
        self.gains[cells] = 0.0
        self.nis_ema[cells] = 1.0
        self.noise.reset(cells)
        diag = np.full(self.nx, 1e-4)
        diag[self.i_soc] = soc_std**2
        diag[self.i_uh] = max(u_h_std, 1e-3) ** 2
        if self.i_bias is not None:
            diag[self.i_bias] = max(bias_std_a, 1e-6) ** 2
        if self.i_ocv is not None:
            diag[self.i_ocv] = self.settings.ocv_error_std_v**2
        self.P[cells] = np.diag(diag)

    # -- Table 3 steps 3-5 --------------------------------------------------------------
    def predict(
        self,
        dt_s: float,
        current_a: np.ndarray,
        params: CellParameters,
        weights: np.ndarray,
    ) -> None:
        b = self.b
        i = current_a - params.current_bias_a
        g = np.power(max(dt_s, 1e-9), params.alpha) / params.c
        den = 1.0 + g / params.r
        a = -weights[..., 1] / den
        mem_w = weights[..., 2:] / den[..., None]  # [N, B, L-1]
        memory = (mem_w * self.hist[..., 1:]).sum(axis=-1)
        drive = g / den * i[:, None] - memory
        a_h = hysteresis_decay(i, dt_s, params.hyst_rate, params.capacity_ah)
        h_target = (1.0 - a_h) * (-np.sign(i)) * params.u_h_max
        d_soc = -i * dt_s / (SECONDS_PER_HOUR * params.capacity_ah)

        # Zeng Eq. 5 is linear in the state for a known current, so the unscented
        # transform of Table 3 steps 3-5 is exact and equals F P Fᵀ with a diagonal F
        # (plus one coupling SOC <- offset): computed directly (same result as
        # propagating sigma points, a fraction of the work).
        cols = [a, np.ones((self.n, 1)), a_h[:, None]]
        if self.i_bias is not None:
            cols.append(np.ones((self.n, 1)))
        if self.i_ocv is not None:
            rho = np.exp(-np.abs(d_soc) / self.settings.ocv_error_soc_length)
            cols.append(rho[:, None])
        f = np.concatenate(cols, axis=1)
        x_pred = np.empty_like(self.x)
        x_pred[:, :b] = a * self.x[:, :b] + drive
        x_pred[:, self.i_soc] = self.x[:, self.i_soc] + d_soc
        x_pred[:, self.i_uh] = a_h * self.x[:, self.i_uh] + h_target
        if self.i_ocv is not None:
            x_pred[:, self.i_ocv] = rho * self.x[:, self.i_ocv]
        if self.i_bias is None:
            P_pred = self.P * (f[:, :, None] * f[:, None, :])
        else:
            # F = diag(f) + c e_soc e_bᵀ, c = dt / 3600 Q: SOC integrates I - b
            c = dt_s / (SECONDS_PER_HOUR * params.capacity_ah)
            x_pred[:, self.i_bias] = self.x[:, self.i_bias]
            x_pred[:, self.i_soc] += c * self.x[:, self.i_bias]
            fp = f[:, :, None] * self.P
            fp[:, self.i_soc, :] += c[:, None] * self.P[:, self.i_bias, :]
            P_pred = fp * f[:, None, :]
            P_pred[:, :, self.i_soc] += c[:, None] * fp[:, :, self.i_bias]
        # process noise: SOC from the current sensor, small for the branches and U_h
        q = np.zeros((self.n, self.nx))
        q[:, :b] = (self.settings.branch_noise_v_per_sqrt_s * np.sqrt(max(dt_s, 1e-3))) ** 2
        sigma_i = self.settings.current_noise_sigma_a(params.capacity_ah)
        q[:, self.i_soc] = (sigma_i * dt_s / (SECONDS_PER_HOUR * params.capacity_ah)) ** 2
        q[:, self.i_uh] = (1e-4 * (1.0 - a_h) + 1e-6) ** 2 + ((1.0 - a_h) * params.u_h_max) ** 2 * 0.01
        # fractional memory covariance (Table 3 step 5): Σ_{j≥2} (w_j/d)^2 P_{k-j}
        q[:, :b] += (mem_w * mem_w * self.var_hist[..., 1:]).sum(axis=-1)
        if self.i_bias is not None:
            walk = self.settings.current_bias_walk_c_per_sqrt_s * params.capacity_ah
            q[:, self.i_bias] = walk * walk * max(dt_s, 1e-3)
        if self.i_ocv is not None:
            q[:, self.i_ocv] = self.settings.ocv_error_std_v**2 * (1.0 - rho * rho)
        P_pred[:, np.arange(self.nx), np.arange(self.nx)] += q
        self.x, self.P = x_pred, P_pred
        self.transition = f

    # -- Table 3 steps 6-8, Eqs. 18-20 --------------------------------------------------
    def update(
        self,
        voltage_v: np.ndarray,
        current_a: np.ndarray,
        temp_c: np.ndarray,
        params: CellParameters,
        active: np.ndarray,
        cell_ocv: CellOcv | None = None,
        surface_deficit: np.ndarray | None = None,
    ) -> None:
        """``surface_deficit[n]`` (optional): bulk − surface SOC of the solid-diffusion
        extension; the OCV is then read at the particle surface, ``OCV(SOC - x)``."""
        b = self.b
        i = current_a - params.current_bias_a
        sqrt_p, bad = robust_cholesky(self.P)
        self.repairs += int(bad.sum())
        X = sigma_points(self.x, sqrt_p, self.gamma)
        soc_s = X[..., self.i_soc]
        if surface_deficit is not None:
            soc_s = soc_s - surface_deficit[:, None]
        drop = params.r_ohm * i
        # the Butler-Volmer term, kept for the fast identifier's output (None: no cell has one)
        self.kinetic_v = None
        if np.any(np.isfinite(params.kinetics_i0_a)):
            self.kinetic_v = kinetic_overpotential(i, params.kinetics_i0_a, temp_c)
            drop = drop + self.kinetic_v
        y = (
            (cell_ocv.ocv(soc_s) if cell_ocv is not None else self.ocv.ocv(soc_s, temp_c[:, None]))
            + X[..., self.i_uh]
            + (X[..., self.i_ocv] if self.i_ocv is not None else 0.0)
            - X[..., :b].sum(axis=-1)
            - drop[:, None]
        )
        y_hat = y @ self.wm
        dy = y - y_hat[:, None]
        st = self.settings
        if self.model_error_per_c_v is None:
            model_err = st.voltage_noise_per_amp(params.capacity_ah) * i
        else:
            model_err = self.model_error_per_c_v / params.capacity_ah * i
        overpotential = i * (params.r_ohm + params.r.sum(axis=1))
        if st.voltage_noise_rel_overpotential:
            model_err = np.hypot(model_err, st.voltage_noise_rel_overpotential * overpotential)
        p_own = (dy * dy) @ self.wc + st.voltage_noise_v**2
        p_yy = p_own + model_err**2
        if st.flat_ocv_noise_v and cell_ocv is not None:
            # the table's value on a run its monotone fit held flat is not known (DESIGN §7 tuning:
            # docs/results/tuning.md, loco_flat_ocv)
            p_yy = p_yy + np.where(cell_ocv.on_flat_run(self.x[:, self.i_soc]), st.flat_ocv_noise_v**2, 0.0)
        e = np.where(active, voltage_v - y_hat, 0.0)
        if st.adaptive_noise_samples:
            p_yy = self.noise.match(e, p_yy, overpotential * overpotential, active)
        p_xy = np.einsum("s,nsi,ns->ni", self.wc, X - self.x[:, None, :], dy)
        k = p_xy / p_yy[:, None]
        k = np.where(active[:, None], k, 0.0)
        self.v_pred = y_hat
        self.innovation, self.innovation_var, self.gain = e, p_yy, k
        # the innovation variance without the current-dependent and learned model-error terms (the
        # state spread and the constant voltage noise): what is left where those are common to the
        # cells of a pack and cancel (the pack-relative capacity estimate)
        self.innovation_var_own = p_own

        # multi-innovation window (Eq. 18-19): newest first
        self.innovations[:, 1:] = self.innovations[:, :-1]
        self.innovations[:, 0] = e
        self.gains[:, 1:] = self.gains[:, :-1]
        self.gains[:, 0] = k
        p = self.innovations.shape[1]
        if p == 1:
            self.x = self.x + k * e[:, None]
            self.x_single = self.x
        else:
            self.x_single = self.x + k * e[:, None]
            self.x_single[:, self.i_soc] = np.clip(self.x_single[:, self.i_soc], *SOC_LIMITS)
            gam = self._innovation_weights(params.alpha[:, min(1, b - 1)], p)
            self.x = self.x + np.einsum("np,npi,np->ni", gam, self.gains, self.innovations)
        self.P = self.P - p_yy[:, None, None] * k[:, :, None] * k[:, None, :]
        self.x[:, self.i_soc] = np.clip(self.x[:, self.i_soc], *SOC_LIMITS)
        nis = np.where(active, e * e / p_yy, 1.0)
        self.nis_ema = 0.98 * self.nis_ema + 0.02 * nis

    def _innovation_weights(self, order: np.ndarray, p: int) -> np.ndarray:
        """``γ_i = |w_{i-1}(n)|`` (Zeng Eq. 20), normalised if so configured; cached
        while the diffusion order is unchanged (it moves only at slow updates)."""
        cached = getattr(self, "_gam_cache", None)
        if cached is not None and np.array_equal(cached[0], order):
            return cached[1]
        gam = np.abs(gl_weights(order, p - 1))
        if self.settings.innovation_weighting == "normalized":
            gam = gam / gam.sum(axis=1, keepdims=True)
        self._gam_cache = (order.copy(), gam)
        return gam

    def push_history(self) -> None:
        """Store this step's posterior branch means and variances in the G-L memory."""
        self.hist[..., 1:] = self.hist[..., :-1]
        self.hist[..., 0] = self.x[:, : self.b]
        self.var_hist[..., 1:] = self.var_hist[..., :-1]
        self.var_hist[..., 0] = self.P[:, np.arange(self.b), np.arange(self.b)]

    def diverged(self) -> np.ndarray:
        """Cells whose filter has diverged: non-finite state, or innovations persistently
        far outside their predicted spread (EMA of the normalised innovation squared)."""
        finite = np.isfinite(self.x).all(axis=1) & np.isfinite(self.P).all(axis=(1, 2))
        return ~finite | (self.nis_ema > self.settings.divergence_sigma**2)

    @property
    def r_adapt(self) -> np.ndarray:
        """Mean extra measurement variance the covariance matching has learned, V² per cell."""
        return self.noise.moments[:, 3].copy()

    @property
    def soc(self) -> np.ndarray:
        return self.x[:, self.i_soc]

    @property
    def current_bias_a(self) -> np.ndarray:
        """Learned current-sensor offset per cell, A (zeros without ``current_bias_state``)."""
        return self.x[:, self.i_bias].copy() if self.i_bias is not None else np.zeros(self.n)

    @property
    def soc_std(self) -> np.ndarray:
        return np.sqrt(np.maximum(self.P[:, self.i_soc, self.i_soc], 0.0))
