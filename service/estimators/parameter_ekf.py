"""EKF over model parameters with the total-derivative output Jacobian (Zeng §2.2.2, Table 1).

The filter estimates a chosen subset of ``[R_ohm, R_ct, C_dl, m, R_df, C_df, n, U_df]``
for every cell, alongside the SOC filter (dual estimation, Zeng Fig. 2).  Parameters
are carried as corrections ``z`` to the profile's values at the cell's temperature:
resistances and CPE coefficients multiplicatively (``θ = θ_profile(T)·z``), orders
additively (``θ = θ_profile(T) + z``) and ``U_df`` as a voltage.  The random walk of
Zeng Eq. 12 therefore also follows the known temperature drift of the profile.

Output (Zeng Eq. 9, in this project's signs, with the SOC filter's posterior state):

    h(θ) = OCV(SOC+) + U_h+ - R_ohm I_k - Σ_b U_b,k(θ) - [U_df if identified]

where ``U_b,k(θ)`` is the implicit G-L step of branch ``b`` from the posterior history.
Jacobian (Table 1): ``C = ∂h/∂θ + ∂h/∂x · A · dx⁺_{k-1}/dθ`` and
``dx⁻_k/dθ = ∂f/∂θ + A dx⁺_{k-1}/dθ``, ``dx⁺_k/dθ = dx⁻_k/dθ - K_k C_k`` with ``K``
the SOC filter's gain.  Table 1 lists the explicit branch derivative both in its
part (1) and inside part (3); here it is counted once (in ``∂h/∂θ``), and the state
path carries only the dependence through earlier steps.  The correction uses the
innovation of the current sample (Zeng Eq. 13 mixes indices).

Zeng Eq. 13 takes a fixed measurement variance ``R``.  With ``adaptive_samples`` the
variance is matched to the identifier's own innovations (Mehra's covariance matching,
:mod:`service.estimators.adaptive_noise`, as the SOC filter does): where the profile's
model form is wrong (the cold, a profile fitted from one drive) the innovations exceed
what ``R`` predicts, and the identifier then moves its parameters by less, instead of
taking every sample of model error as information about them.
"""

from __future__ import annotations

import numpy as np

from service.cell.fractional import gl_weights
from service.cell.profile import CellParameters
from service.estimators.adaptive_noise import AdaptiveNoise

#: name -> (branch index or None, kind) ; kind: "mul" multiplicative, "add" additive, "volt"
PARAMETERS: dict[str, tuple[int | None, str]] = {
    "r_ohm": (None, "mul"),
    "r_ct": (0, "mul"),
    "c_dl": (0, "mul"),
    "m": (0, "add"),
    "r_df": (1, "mul"),
    "c_df": (1, "mul"),
    "n": (1, "add"),
    "u_df": (1, "volt"),
}
ORDER_LIMITS = (0.3, 1.0)
RELATIVE_LIMITS = (1.0 / 3.0, 3.0)
U_DF_LIMITS = (-0.5, 0.5)


def apply_corrections(nominal: CellParameters, names: list[str], z: np.ndarray, out: CellParameters) -> None:
    """Write ``nominal`` corrected by ``z[N, len(names)]`` into ``out`` (in place)."""
    for col, name in enumerate(names):
        branch, kind = PARAMETERS[name]
        if kind == "volt":
            continue
        if name == "r_ohm":
            out.r_ohm = nominal.r_ohm * z[:, col]
        elif name in ("r_ct", "r_df"):
            out.r[:, branch] = nominal.r[:, branch] * z[:, col]
        elif name in ("c_dl", "c_df"):
            out.c[:, branch] = nominal.c[:, branch] * z[:, col]
        else:
            out.alpha[:, branch] = np.clip(nominal.alpha[:, branch] + z[:, col], *ORDER_LIMITS)


def branch_step_and_derivatives(
    hist: np.ndarray, i: np.ndarray, dt_s: float, r: np.ndarray, c: np.ndarray, alpha: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Implicit G-L branch step ``U_k`` and ``∂U_k/∂R, ∂U_k/∂C, ∂U_k/∂α`` (all ``[N]``).

    ``U = (g I - M)/(1 + g/R)``, ``g = h^α/C``, ``M = Σ_{j≥1} w_j U_{k-j}``.  The α
    derivative is a forward difference (the weights depend on α too).
    """
    h = max(dt_s, 1e-9)

    def step(a: np.ndarray, w: np.ndarray) -> np.ndarray:
        g = np.power(h, a) / c
        return (g * i - np.einsum("nj,nj->n", w[:, 1:], hist)) / (1.0 + g / r)

    g = np.power(h, alpha) / c
    den = 1.0 + g / r
    u = (g * i - np.einsum("nj,nj->n", weights[:, 1:], hist)) / den
    du_dr = u * g / (den * r * r)
    du_dc = (-g * i / c) / den + u * g / (r * c * den)
    d = 1e-6  # forward difference: one extra weight evaluation per step
    L = hist.shape[-1]
    du_da = (step(alpha + d, gl_weights(alpha + d, L)) - u) / d
    return u, du_dr, du_dc, du_da


class ParameterEkf:
    """Vectorised EKF over the parameters ``names`` of ``n_cells`` cells (Zeng Eqs. 11-13)."""

    def __init__(
        self,
        names: list[str],
        n_cells: int,
        n_states: int,
        process_rel: float,
        voltage_noise_v: float,
        init_rel: float = 0.1,
        adaptive_samples: int = 0,
        correlation_cap: float = 1.0,
    ) -> None:
        unknown = [n for n in names if n not in PARAMETERS]
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}; known: {list(PARAMETERS)}")
        self.names = list(names)
        self.n = n_cells
        self.np = len(names)
        #: the profile's values: relative factors 1, order and voltage offsets 0
        self.z0 = np.array([0.0 if PARAMETERS[k][1] != "mul" else 1.0 for k in names])
        self.z = np.tile(self.z0, (n_cells, 1))
        sig = np.array([init_rel if PARAMETERS[k][1] == "mul" else (0.05 if PARAMETERS[k][1] == "add" else 0.02) for k in names])
        #: the prior a (re)started cell's parameters carry: back at the profile's values, as unsure as at first
        self.P0 = np.diag(sig**2)
        self.P = np.tile(self.P0, (n_cells, 1, 1))
        q = np.array([process_rel if PARAMETERS[k][1] != "volt" else 1e-3 for k in names])
        self.Q = np.diag(q**2)
        self.R = voltage_noise_v**2
        self.measurement = "level"
        self._prev: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.D = np.zeros((n_cells, n_states, self.np))  # dx+/dθ
        self.updates = 0
        self._volt = [c for c, k in enumerate(names) if PARAMETERS[k][1] == "volt"]
        # bounds of z per column (:meth:`_clip`); the orders' depend on the profile and are set per step
        limits = {"mul": RELATIVE_LIMITS, "add": (-np.inf, np.inf), "volt": U_DF_LIMITS}
        bounds = np.array([limits[PARAMETERS[k][1]] for k in names])
        self._lo = np.tile(bounds[:, 0], (n_cells, 1))
        self._hi = np.tile(bounds[:, 1], (n_cells, 1))
        self._order_cols = [(c, PARAMETERS[k][0]) for c, k in enumerate(names) if PARAMETERS[k][1] == "add"]
        self._identifies_df_voltage = bool(self._volt)
        #: covariance matching of the identifier's own innovations (``adaptive_samples`` > 0), as the
        #: SOC filter matches its own: model-form error the fixed ``R`` does not describe (the cold, a
        #: fit from one drive) then slows the identifier instead of moving the parameters by it
        self.noise = (AdaptiveNoise(n_cells, adaptive_samples, correlation_cap=correlation_cap)
                      if adaptive_samples else None)

    def reset(self, cells: np.ndarray) -> None:
        """Restart ``cells``: parameters back at the profile's with the prior's spread, so a cell
        restarted after a divergence identifies afresh instead of keeping a shrunk covariance."""
        self.z[cells] = self.z0
        self.P[cells] = self.P0
        self.D[cells] = 0.0
        if self.noise is not None:
            self.noise.reset(cells)
        if self._prev is not None:
            self._prev[3][cells] = False  # no voltage difference across a restart

    def difference_state(self, n_cells: int) -> dict[str, np.ndarray]:
        """The previous sample kept by the 'difference' input (zeros and inactive if none)."""
        if self._prev is None:
            return {"fast_prev_v": np.zeros(n_cells), "fast_prev_h": np.zeros(n_cells),
                    "fast_prev_c": np.zeros((n_cells, self.np)), "fast_prev_active": np.zeros(n_cells, dtype=bool)}
        v, h, c, a = self._prev
        return {"fast_prev_v": v, "fast_prev_h": h, "fast_prev_c": c, "fast_prev_active": a}

    def set_difference_state(self, prev: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None) -> None:
        """Restore :meth:`difference_state`'s arrays ``(v, h, c, active)``; None = no previous sample."""
        if prev is None:
            self._prev = None
        else:
            v, h, c, active = prev
            self._prev = (v.copy(), h.copy(), c.copy(), active.astype(bool).copy())

    @property
    def u_df(self) -> np.ndarray | None:
        return self.z[:, self._volt[0]] if self._volt else None

    def update(
        self,
        *,
        nominal: CellParameters,
        params: CellParameters,
        weights: np.ndarray,
        hist: np.ndarray,
        x_post: np.ndarray,
        soc_slope: np.ndarray,
        ocv_post: np.ndarray,
        gain: np.ndarray,
        transition: np.ndarray,
        current_a: np.ndarray,
        dt_s: float,
        voltage_v: np.ndarray,
        active: np.ndarray,
        kinetic_v: np.ndarray | None = None,
    ) -> None:
        """One EKF step for every cell (inactive cells only predict).

        ``kinetic_v`` is the Butler-Volmer term of the output (:func:`kinetic_overpotential`)
        when the profile has one; it depends on no identified parameter, so it only shifts ``h``.
        """
        n_b = params.r.shape[1]
        i_soc, i_uh = n_b, n_b + 1
        i = current_a - params.current_bias_a
        if self._volt:
            # Zeng Eq. 12 makes U_df a random walk, which lags the diffusion voltage and lets
            # R_ohm/R_ct absorb the lag; its prediction is the SOC filter's diffusion state.
            self.z[:, self._volt[0]] = x_post[:, 1]
        # explicit output and derivatives
        h = ocv_post + x_post[:, i_uh] - params.r_ohm * i
        if kinetic_v is not None:
            h = h - kinetic_v
        dh = np.zeros((self.n, self.np))
        df = np.zeros((self.n, x_post.shape[1], self.np))  # ∂f/∂θ
        branch_cols: dict[int, dict[str, int]] = {}
        for col, name in enumerate(self.names):
            br, _ = PARAMETERS[name]
            if br is not None:
                branch_cols.setdefault(br, {})[name] = col
        dhdx = np.zeros((self.n, x_post.shape[1]))
        dhdx[:, i_soc] = soc_slope
        dhdx[:, i_uh] = 1.0
        for b in range(n_b):
            cols = branch_cols.get(b, {})
            if b == 1 and self._identifies_df_voltage:
                h = h - self.u_df
                dh[:, self._volt[0]] = -1.0
                continue
            dhdx[:, b] = -1.0
            if not cols:
                h = h - x_post[:, b]
                continue
            u, du_dr, du_dc, du_da = branch_step_and_derivatives(
                hist[:, b], i, dt_s, params.r[:, b], params.c[:, b], params.alpha[:, b], weights[:, b]
            )
            h = h - u
            for name, col in cols.items():
                if name in ("r_ct", "r_df"):
                    s = du_dr * nominal.r[:, b]
                elif name in ("c_dl", "c_df"):
                    s = du_dc * nominal.c[:, b]
                else:
                    s = du_da
                dh[:, col] = -s
                df[:, b, col] = s
        if "r_ohm" in self.names:
            dh[:, self.names.index("r_ohm")] = -i * nominal.r_ohm
        # total derivative through the state (Table 1 parts 2-3)
        d_prior_hist = transition[:, :, None] * self.D
        c_row = dh + np.einsum("ni,nip->np", dhdx, d_prior_hist)
        d_prior = df + d_prior_hist
        self.D = d_prior - gain[:, :, None] * c_row[:, None, :]

        # EKF (Zeng Eqs. 12-13): random walk, then correction with this sample's innovation
        self.P = self.P + self.Q
        e = voltage_v - h
        if self.measurement == "difference":
            # feature separation: the change of voltage from one sample to the next carries
            # the fast dynamics but almost none of the (slowly varying) OCV, so SOC errors do
            # not leak into R_ohm, R_ct, C_dl, m.
            prev = self._prev
            self._prev = (voltage_v.copy(), h.copy(), c_row.copy(), active.copy())
            if prev is None:
                active = np.zeros_like(active)
            else:
                e = e - (prev[0] - prev[1])
                c_row = c_row - prev[2]
                active = active & prev[3]
        e = np.where(active, e, 0.0)
        pc = np.einsum("nij,nj->ni", self.P, c_row)
        s = np.einsum("ni,ni->n", c_row, pc) + self.R
        if self.noise is not None:  # one matched variance per cell (the 'uniform' shape)
            s = self.noise.match(e, s, np.zeros_like(s), active)
        k = pc / s[:, None]
        k = np.where(active[:, None], k, 0.0)
        self.z = self.z + k * e[:, None]
        self.P = self.P - s[:, None, None] * k[:, :, None] * k[:, None, :]
        self.P = 0.5 * (self.P + np.swapaxes(self.P, 1, 2))
        self._clip(nominal)
        self.updates += 1

    def _clip(self, nominal: CellParameters) -> None:
        """Keep every parameter inside physical bounds (relative to the profile)."""
        lo, hi = self._lo.copy(), self._hi.copy()
        for col, br in self._order_cols:  # orders: absolute limits, relative to the profile's value
            lo[:, col] = ORDER_LIMITS[0] - nominal.alpha[:, br]
            hi[:, col] = ORDER_LIMITS[1] - nominal.alpha[:, br]
        np.clip(self.z, lo, hi, out=self.z)
        bad = ~np.isfinite(self.z).all(axis=1) | ~np.isfinite(self.P).all(axis=(1, 2))
        if bad.any():
            self.reset(bad)
