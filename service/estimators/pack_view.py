"""The pack as a BMS reports it: SOC min / mean / max, usable SOC, energy and imbalance.

Cells of a series string carry the same current, so the pack can give no more charge than
its emptiest cell holds and take no more than its fullest cell has room for.  With cell
``i`` at ``SOC_i`` of capacity ``C_i`` (Ah):

- usable discharge ``D = min_i SOC_i·C_i`` (Ah the weakest cell can still give), its cell
  is the **weakest cell**;
- usable charge headroom ``H = min_i (1 − SOC_i)·C_i`` (Ah the fullest cell can still take);
- **usable SOC** ``= D / (D + H)``, the usual definition: the pack's SOC over the capacity
  it can cycle between its two limits (undefined, NaN, when ``D + H = 0``);
- **imbalance** ``= max_i SOC_i·C_i − min_i SOC_i·C_i`` (Ah);
- **remaining energy** ``= Σ_i C_i ∫_0^{SOC_i} OCV_i(s) ds`` (Wh): the energy stored in the
  cells above each one's empty point, with the OCV integrated *exactly* over the profile's
  OCV model (:meth:`service.cell.profile.CellProfile.ocv_table`, piecewise linear in SOC on
  its grid, linear in temperature between rows) at each cell's temperature; and **usable
  energy**, the part of it the string can deliver before its weakest cell is empty (each
  cell discharged by ``D`` Ah from its SOC).  Open-circuit energy: the loss in the cells'
  resistance at the discharge rate is not subtracted, and hysteresis and the entropic
  temperature term are left out.

Capacities come in as a per-cell array (``profile.effective_capacity_ah`` for every cell
today; an online per-cell capacity estimate can be passed instead).  SOC is clipped to
[0, 1] first: an estimate a hair outside is a cell at its limit.  Cells with a non-finite
SOC or a non-positive / non-finite capacity are left out (``valid`` can drop more); the
indices in the result are those of the input arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.cell.ocv import OcvTable, temperature_rows


class OcvEnergy:
    """``∫_0^soc OCV(s, T) ds`` (V per unit SOC; × capacity in Ah gives Wh), exact for the table.

    The table is piecewise linear in SOC on a uniform grid, so the integral up to grid
    point ``j`` is a trapezoid sum (computed once per temperature row) and the part inside
    the last interval is the exact area under its line.
    """

    def __init__(self, table: OcvTable) -> None:
        self.table = table
        v = np.asarray(table.ocv_v, dtype=float)
        self.n_intervals = v.shape[1] - 1
        h = 1.0 / self.n_intervals
        self._v = v
        self._cum = np.concatenate([np.zeros((v.shape[0], 1)), np.cumsum(0.5 * h * (v[:, 1:] + v[:, :-1]), axis=1)],
                                   axis=1)

    def integral(self, soc: np.ndarray, temp_c: np.ndarray | float = 25.0) -> np.ndarray:
        """``∫_0^soc OCV ds`` at each ``soc`` (clipped to [0, 1]) and ``temp_c`` (broadcast)."""
        soc, temp_c = np.broadcast_arrays(np.clip(np.asarray(soc, float), 0.0, 1.0), np.asarray(temp_c, float))
        k0, k1, f = temperature_rows(self.table.temps_c, temp_c)
        n = self.n_intervals
        x = soc * n
        j = np.minimum(np.floor(x).astype(int), n - 1)
        u = x - j  # position inside interval j, in [0, 1]

        def row(k: np.ndarray) -> np.ndarray:
            v0, v1 = self._v[k, j], self._v[k, j + 1]
            return self._cum[k, j] + (u / n) * (v0 + 0.5 * u * (v1 - v0))

        lo = row(k0)
        return lo + f * (row(k1) - lo)


@dataclass(frozen=True)
class PackView:
    """One pack view (SOC as fractions in [0, 1]; ``None``/NaN where no cell counts).

    Indices are 0-based cells of the input arrays.  ``weakest_cell`` limits discharge,
    ``fullest_cell`` limits charge.
    """

    n_cells: int
    n_used: int
    soc_min: float
    soc_mean: float
    soc_max: float
    cell_min: int | None
    cell_max: int | None
    usable_soc: float
    usable_discharge_ah: float
    usable_charge_ah: float
    imbalance_ah: float
    weakest_cell: int | None
    fullest_cell: int | None
    remaining_energy_wh: float
    usable_energy_wh: float

    @property
    def ok(self) -> bool:
        """True when at least one cell counted."""
        return self.n_used > 0


def empty_view(n_cells: int) -> PackView:
    nan = float("nan")
    return PackView(n_cells=n_cells, n_used=0, soc_min=nan, soc_mean=nan, soc_max=nan, cell_min=None, cell_max=None,
                    usable_soc=nan, usable_discharge_ah=nan, usable_charge_ah=nan, imbalance_ah=nan,
                    weakest_cell=None, fullest_cell=None, remaining_energy_wh=nan, usable_energy_wh=nan)


def pack_view(
    soc: np.ndarray,
    capacity_ah: np.ndarray | float,
    energy: OcvEnergy,
    temp_c: np.ndarray | float = 25.0,
    valid: np.ndarray | None = None,
) -> PackView:
    """The :class:`PackView` of cells at ``soc`` with capacities ``capacity_ah`` (per cell or one
    value) and temperatures ``temp_c`` (°C, per cell or one; non-finite reads as 25 °C).

    ``valid`` (bool per cell, optional) leaves cells out in addition to those without a
    finite SOC and a positive capacity.  Never raises for bad values: a pack with no cell
    left gives :func:`empty_view`.
    """
    soc = np.asarray(soc, dtype=float).ravel()
    n = soc.size
    cap = np.broadcast_to(np.asarray(capacity_ah, dtype=float).ravel(), (n,)) if n else np.zeros(0)
    temp = np.broadcast_to(np.asarray(temp_c, dtype=float).ravel(), (n,)) if n else np.zeros(0)
    use = np.isfinite(soc) & np.isfinite(cap) & (cap > 0.0)
    if valid is not None:
        use &= np.broadcast_to(np.asarray(valid, dtype=bool).ravel(), (n,))
    if not use.any():
        return empty_view(n)
    idx = np.flatnonzero(use)
    s = np.clip(soc[idx], 0.0, 1.0)
    c = cap[idx]
    t = np.where(np.isfinite(temp[idx]), temp[idx], 25.0)
    held = s * c  # Ah each cell can give
    room = (1.0 - s) * c  # Ah each cell can take
    w, f = int(np.argmin(held)), int(np.argmin(room))
    d, h = float(held[w]), float(room[f])
    total = d + h
    stored = energy.integral(s, t) * c  # Wh above each cell's empty point
    after = energy.integral(s - d / c, t) * c  # each cell discharged by d Ah
    lo, hi = int(np.argmin(s)), int(np.argmax(s))
    return PackView(
        n_cells=n,
        n_used=int(idx.size),
        soc_min=float(s[lo]),
        soc_mean=float(s.mean()),
        soc_max=float(s[hi]),
        cell_min=int(idx[lo]),
        cell_max=int(idx[hi]),
        usable_soc=d / total if total > 0.0 else float("nan"),
        usable_discharge_ah=d,
        usable_charge_ah=h,
        imbalance_ah=float(held.max() - d),
        weakest_cell=int(idx[w]),
        fullest_cell=int(idx[f]),
        remaining_energy_wh=float(stored.sum()),
        usable_energy_wh=float((stored - after).sum()),
    )
