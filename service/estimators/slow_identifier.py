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

from service.cell.fractional import cpe_step, gl_weights, push_history, resized_history
from service.cell.units import SECONDS_PER_HOUR
from service.estimators.parameter_ekf import ORDER_LIMITS, RELATIVE_LIMITS

NAMES = ("r_df", "c_df", "n")
_PERTURB = np.array([0.02, 0.02, 0.01])


class SlowIdentifier:
    """Per-cell slow EKF.  Samples are buffered once for the pack; every cell keeps its own
    interval (start index and initial memory), so a cell identified in a pack gets exactly
    the numbers it would get alone."""

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
        self.start = np.zeros(n_cells, dtype=int)  # each cell's interval start in the buffer
        self.ring = np.zeros((n_cells, memory_length))  # fast U_df, newest first
        self.hist0 = np.zeros((n_cells, memory_length))
        self.moved = np.zeros(n_cells)
        self.updates = 0

    def resize_memory(self, length: int) -> None:
        """Hold ``length`` samples of U_df memory, the newest kept (:func:`service.cell.fractional.resized_history`)."""
        self.L = length
        self.ring = resized_history(self.ring, length)
        self.hist0 = resized_history(self.hist0, length)

    def reset(self, cells: np.ndarray) -> None:
        self.z[cells] = np.array([1.0, 1.0, 0.0])

    def _restart(self, cells: np.ndarray) -> None:
        """Begin a new interval for ``cells`` at the end of the buffer."""
        self.hist0[cells] = self.ring[cells]
        self.start[cells] = self.length
        self.moved[cells] = 0.0

    def record(self, dt_s: float, current_a: np.ndarray, u_df_meas: np.ndarray, capacity_ah: np.ndarray) -> None:
        """Buffer one sample of the fast path (cheap; called every step)."""
        if self.length == self.capacity:  # drop what no cell needs; a cell stuck at 0 restarts
            first = int(self.start.min())
            if first == 0:
                stuck = self.start == 0
                self.hist0[stuck] = self.ring[stuck]
                self.start[stuck] = self.length
                first = int(self.start.min())
            keep = self.length - first
            self.dt[:keep] = self.dt[first:self.length]
            self.i[:keep] = self.i[first:self.length]
            self.meas[:keep] = self.meas[first:self.length]
            self.start -= first
            self.length = keep
        self.moved += np.abs(current_a) * dt_s / (SECONDS_PER_HOUR * capacity_ah)
        k = self.length
        self.dt[k] = dt_s
        self.i[k] = current_a
        self.meas[k] = u_df_meas
        self.length += 1
        push_history(self.ring, u_df_meas)

    def due_cells(self) -> np.ndarray:
        """Cells whose interval has passed ``soc_delta`` of charge (and holds ≥ 2 samples)."""
        return (self.moved >= self.soc_delta) & (self.length - self.start >= 2)

    def update(self, r_df: np.ndarray, c_df: np.ndarray, n: np.ndarray, cells: np.ndarray | None = None) -> np.ndarray:
        """Run the slow update for every due cell; ``r_df, c_df, n`` are the profile values at T.

        Due cells outside ``cells`` (default all) start a new interval without a correction.
        Returns the mask of corrected cells.
        """
        due = self.due_cells()
        if not due.any():
            return np.zeros(self.n, dtype=bool)
        allowed = np.ones(self.n, dtype=bool) if cells is None else np.asarray(cells, dtype=bool)
        fit = due & allowed
        corrected = np.zeros(self.n, dtype=bool)
        if fit.any():
            idx_cells = np.flatnonzero(fit)
            corrected[idx_cells] = self._correct(idx_cells, r_df, c_df, n)
        self._restart(due)
        self.updates += int(fit.any())
        return corrected

    def _correct(self, cells: np.ndarray, r_df: np.ndarray, c_df: np.ndarray, n: np.ndarray) -> np.ndarray:
        """EKF correction of ``cells`` from a re-simulation of each one's own interval."""
        m = cells.size
        z = self.z[cells]
        zs = np.repeat(z[:, None, :], 4, axis=1)
        for j in range(3):
            zs[:, j + 1, j] += _PERTURB[j]
        r = r_df[cells, None] * zs[..., 0]
        c = c_df[cells, None] * zs[..., 1]
        a = np.clip(n[cells, None] + zs[..., 2], *ORDER_LIMITS)
        w = gl_weights(a, self.L)
        hist = np.repeat(self.hist0[cells][:, None, :], 4, axis=1)
        first = self.start[cells]
        k0 = int(first.min())
        steps = self.length - first  # per cell
        # sample points: evenly spaced over the last two thirds of each cell's own interval
        frac = np.linspace(0.0, 1.0, self.points)
        pts = (first[:, None] + (steps // 3)[:, None] + frac[None, :] * (steps - 1 - steps // 3)[:, None]).astype(int)
        pred = np.empty((m, 4, self.points))
        for k in range(k0, self.length):
            live = k >= first
            u = cpe_step(hist, self.i[k, cells][:, None], self.dt[k], r, c, a, w)
            if live.all():
                push_history(hist, u)
            else:
                pushed = hist.copy()
                push_history(pushed, u)
                hist = np.where(live[:, None, None], pushed, hist)
            hit = pts == k
            if hit.any():
                ci, pi = np.nonzero(hit)
                pred[ci, :, pi] = u[ci]
        meas = self.meas[pts, cells[:, None]]  # [m, M]
        H = np.swapaxes((pred[:, 1:, :] - pred[:, :1, :]) / _PERTURB[None, :, None], 1, 2)  # [m, M, 3]
        e = meas - pred[:, 0, :]
        P = self.P[cells] + self.Q
        S = H @ P @ np.swapaxes(H, 1, 2) + self.R * np.eye(self.points)
        K = P @ np.swapaxes(H, 1, 2) @ np.linalg.inv(S)
        ok = np.isfinite(K).all(axis=(1, 2)) & np.isfinite(e).all(axis=1)
        dz = np.einsum("nij,nj->ni", K, np.where(np.isfinite(e), e, 0.0))
        znew = np.where(ok[:, None], z + dz, z)
        newP = P - K @ S @ np.swapaxes(K, 1, 2)
        self.P[cells] = np.where(ok[:, None, None], 0.5 * (newP + np.swapaxes(newP, 1, 2)), P)
        znew[:, 0] = np.clip(znew[:, 0], *RELATIVE_LIMITS)
        znew[:, 1] = np.clip(znew[:, 1], *RELATIVE_LIMITS)
        znew[:, 2] = np.clip(znew[:, 2], ORDER_LIMITS[0] - n[cells], ORDER_LIMITS[1] - n[cells])
        self.z[cells] = znew
        return ok
