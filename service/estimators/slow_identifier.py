"""Slow-rate EKF over the diffusion branch ``[R_df, C_df, n]`` (Zeng §2.2.3, Eqs. 14-16, Table 2).

The measurement is the fast identifier's ``U_df`` (Zeng Eq. 14).  The filter updates
only once SOC has moved by ``slow_soc_delta`` since its last update, measured as
charge throughput ``Σ|I|h/3600Q`` (the SOC filter's own corrections do not count).  At an update it
re-simulates the diffusion branch over the samples since the last update (from the
fast filter's ``U_df`` history as initial memory) with the current ``θ_slow`` and with
each parameter perturbed, compares the simulation with the fast ``U_df`` at a few
points of the interval, and corrects ``θ_slow`` with that vector innovation.  The
derivative ``dU_df/dθ`` is therefore a finite difference through the G-L recursion
(the role of Table 2's recursion), computed off the fast path: the service runs
:meth:`SlowIdentifier.update` in its own task at its own rate.
"""

from __future__ import annotations

import numpy as np

from service.cell.fractional import cpe_step, gl_weights, push_history
from service.estimators.parameter_ekf import ORDER_LIMITS, RELATIVE_LIMITS

NAMES = ("r_df", "c_df", "n")
_PERTURB = np.array([0.02, 0.02, 0.01])


class SlowIdentifier:
    def __init__(
        self,
        n_cells: int,
        memory_length: int,
        soc_delta: float,
        process_rel: float,
        u_df_noise_v: float = 0.003,
        points: int = 6,
        capacity: int = 4096,
    ) -> None:
        self.n = n_cells
        self.L = memory_length
        self.soc_delta = soc_delta
        self.z = np.tile(np.array([1.0, 1.0, 0.0]), (n_cells, 1))
        self.P = np.tile(np.diag([0.1, 0.1, 0.05]) ** 2, (n_cells, 1, 1))
        self.Q = np.diag(np.array([process_rel, process_rel, process_rel / 2]) ** 2)
        self.R = u_df_noise_v**2
        self.points = points
        self.capacity = capacity
        self.dt = np.zeros(capacity)
        self.i = np.zeros((capacity, n_cells))
        self.meas = np.zeros((capacity, n_cells))
        self.length = 0
        self.ring = np.zeros((n_cells, memory_length))  # fast U_df, newest first
        self.hist0 = np.zeros((n_cells, memory_length))
        self.moved = np.zeros(n_cells)
        self.updates = 0

    def reset(self, cells: np.ndarray) -> None:
        self.z[cells] = np.array([1.0, 1.0, 0.0])

    def record(self, dt_s: float, current_a: np.ndarray, u_df_meas: np.ndarray, capacity_ah: np.ndarray) -> None:
        """Buffer one sample of the fast path (cheap; called every step)."""
        self.moved += np.abs(current_a) * dt_s / (3600.0 * capacity_ah)
        if self.length == self.capacity:  # long rest: restart the interval here
            self.hist0 = self.ring.copy()
            self.length = 0
        k = self.length
        self.dt[k] = dt_s
        self.i[k] = current_a
        self.meas[k] = u_df_meas
        self.length += 1
        push_history(self.ring, u_df_meas)

    def due(self) -> bool:
        return self.length >= 2 and bool(self.moved.max() >= self.soc_delta)

    def update(self, r_df: np.ndarray, c_df: np.ndarray, n: np.ndarray, cells: np.ndarray | None = None) -> bool:
        """Run one slow update if due; ``r_df, c_df, n`` are the profile values at T.

        The update fires pack-wide when the cell that has passed the most charge reaches
        ``soc_delta`` (in a series pack every cell passes the same charge); only ``cells``
        (default all) take the correction.
        """
        if not self.due():
            return False
        steps = self.length
        z = self.z
        zs = np.repeat(z[:, None, :], 4, axis=1)
        for j in range(3):
            zs[:, j + 1, j] += _PERTURB[j]
        r = r_df[:, None] * zs[..., 0]
        c = c_df[:, None] * zs[..., 1]
        a = np.clip(n[:, None] + zs[..., 2], *ORDER_LIMITS)
        w = gl_weights(a, self.L)
        hist = np.repeat(self.hist0[:, None, :], 4, axis=1)
        idx = np.unique(np.linspace(steps // 3, steps - 1, self.points).astype(int))
        pred = np.empty((self.n, 4, idx.size))
        want = {int(k): col for col, k in enumerate(idx)}
        for k in range(steps):
            u = cpe_step(hist, self.i[k][:, None], self.dt[k], r, c, a, w)
            push_history(hist, u)
            if k in want:
                pred[:, :, want[k]] = u
        meas = self.meas[idx].T  # [N, M]
        H = np.swapaxes((pred[:, 1:, :] - pred[:, :1, :]) / _PERTURB[None, :, None], 1, 2)  # [N, M, 3]
        e = meas - pred[:, 0, :]
        P = self.P + self.Q
        S = H @ P @ np.swapaxes(H, 1, 2) + self.R * np.eye(idx.size)
        K = P @ np.swapaxes(H, 1, 2) @ np.linalg.inv(S)
        ok = np.isfinite(K).all(axis=(1, 2)) & np.isfinite(e).all(axis=1)
        if cells is not None:
            ok &= cells
        dz = np.einsum("nij,nj->ni", K, np.where(np.isfinite(e), e, 0.0))
        self.z = np.where(ok[:, None], z + dz, z)
        newP = P - K @ S @ np.swapaxes(K, 1, 2)
        self.P = np.where(ok[:, None, None], 0.5 * (newP + np.swapaxes(newP, 1, 2)), P)
        self.z[:, 0] = np.clip(self.z[:, 0], *RELATIVE_LIMITS)
        self.z[:, 1] = np.clip(self.z[:, 1], *RELATIVE_LIMITS)
        self.z[:, 2] = np.clip(self.z[:, 2], ORDER_LIMITS[0] - n, ORDER_LIMITS[1] - n)
        self.hist0 = self.ring.copy()
        self.length = 0
        self.moved[:] = 0.0
        self.updates += 1
        return True
