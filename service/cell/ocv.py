"""Open-circuit voltage OCV(SOC, T): table lookup, slope and inverse.

The table is resampled once onto a uniform SOC grid so a lookup for a whole pack is
an index computation, not a search.  Outside [0, 1] the end slopes extrapolate
linearly (sigma points of the UKF may step outside).  Between temperatures the
lookup is linear; outside the table's temperatures it holds the nearest row.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

GRID_POINTS = 201
#: outside [0, 1] the OCV continues with the mean slope over this much SOC at each end
EXTRAPOLATION_SPAN = 0.1


def temperature_rows(temps_c: np.ndarray, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows ``k0, k1`` of a table on sorted ``temps_c`` around each ``temp_c`` and the weight
    ``f`` of ``k1`` (linear in T; outside the table the nearest row holds)."""
    if temps_c.size == 1:
        z = np.zeros(np.shape(temp_c), dtype=int)
        return z, z, np.zeros(np.shape(temp_c))
    t = np.clip(temp_c, temps_c[0], temps_c[-1])
    k1 = np.clip(np.searchsorted(temps_c, t, side="right"), 1, temps_c.size - 1)
    k0 = k1 - 1
    f = (t - temps_c[k0]) / (temps_c[k1] - temps_c[k0])
    return k0, k1, f


def grid_lookup(table: np.ndarray, k0: np.ndarray, k1: np.ndarray, f: np.ndarray, soc: np.ndarray) -> np.ndarray:
    """Bilinear lookup in ``table[k, s]`` on a uniform SOC grid over [0, 1] (SOC clipped to
    it), between rows ``k0`` and ``k1`` with weight ``f`` (:func:`temperature_rows`)."""
    n = table.shape[1] - 1
    x = np.clip(soc, 0.0, 1.0) * n
    i0 = np.clip(np.floor(x).astype(int), 0, n - 1)
    u = x - i0
    lo = table[k0, i0] + u * (table[k0, i0 + 1] - table[k0, i0])
    hi = table[k1, i0] + u * (table[k1, i0 + 1] - table[k1, i0])
    return lo + f * (hi - lo)


@dataclass(frozen=True)
class OcvTable:
    """``ocv_v[k, s]`` at ``temps_c[k]`` and uniform ``soc[s]`` in [0, 1]."""

    temps_c: np.ndarray
    ocv_v: np.ndarray

    @classmethod
    def from_points(
        cls, soc: np.ndarray, ocv_v: np.ndarray, temps_c: np.ndarray | None = None
    ) -> OcvTable:
        """Build from points; ``ocv_v`` is ``[S]`` or ``[K, S]``.  Enforces monotone rows."""
        soc = np.asarray(soc, dtype=float)
        ocv = np.atleast_2d(np.asarray(ocv_v, dtype=float))
        temps = np.atleast_1d(np.asarray(25.0 if temps_c is None else temps_c, dtype=float))
        if ocv.shape != (temps.size, soc.size):
            raise ValueError(
                f"OCV table shape {ocv.shape} does not match {temps.size} temperatures x {soc.size} SOC points"
            )
        if soc.size < 2 or np.any(np.diff(soc) <= 0):
            raise ValueError("OCV table SOC points must be strictly increasing (at least 2)")
        if not np.all(np.isfinite(ocv)):
            raise ValueError("OCV table holds non-finite voltages")
        order = np.argsort(temps)
        grid = np.linspace(0.0, 1.0, GRID_POINTS)
        rows = []
        for row in ocv[order]:
            # extrapolate to [0, 1] with the end slopes, then force monotone increasing
            slope_lo = (row[1] - row[0]) / (soc[1] - soc[0])
            slope_hi = (row[-1] - row[-2]) / (soc[-1] - soc[-2])
            r = np.interp(grid, soc, row)
            r = np.where(grid < soc[0], row[0] + slope_lo * (grid - soc[0]), r)
            r = np.where(grid > soc[-1], row[-1] + slope_hi * (grid - soc[-1]), r)
            rows.append(make_monotone(r))
        return cls(temps_c=temps[order], ocv_v=np.array(rows))

    # -- lookups ------------------------------------------------------------------------
    def _rows_at(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return temperature_rows(self.temps_c, temp_c)

    def ocv(self, soc: np.ndarray, temp_c: np.ndarray | float = 25.0) -> np.ndarray:
        """OCV at ``soc`` and ``temp_c`` (broadcast together).  Outside [0, 1] it continues
        with the mean slope of the outer 10 % of SOC (:data:`EXTRAPOLATION_SPAN`), not the
        often near-vertical last segment."""
        soc, temp_c = np.broadcast_arrays(np.asarray(soc, float), np.asarray(temp_c, float))
        k0, k1, f = self._rows_at(temp_c)
        v = grid_lookup(self.ocv_v, k0, k1, f, soc)
        lo_ext, hi_ext = self._extrapolation_at(k0, k1, f)
        return v + lo_ext * np.minimum(soc, 0.0) + hi_ext * np.maximum(soc - 1.0, 0.0)

    def _extrapolation_at(self, k0: np.ndarray, k1: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Extrapolation slopes below 0 and above 1, interpolated between temperature rows."""
        lo_s, hi_s = self.extrapolation_slopes
        return lo_s[k0] + f * (lo_s[k1] - lo_s[k0]), hi_s[k0] + f * (hi_s[k1] - hi_s[k0])

    @cached_property
    def extrapolation_slopes(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-row slopes (V per unit SOC) used below 0 and above 1."""
        k = int(round(EXTRAPOLATION_SPAN * (GRID_POINTS - 1)))
        lo = (self.ocv_v[:, k] - self.ocv_v[:, 0]) / EXTRAPOLATION_SPAN
        hi = (self.ocv_v[:, -1] - self.ocv_v[:, -1 - k]) / EXTRAPOLATION_SPAN
        return lo, hi

    def slope(self, soc: np.ndarray, temp_c: np.ndarray | float = 25.0) -> np.ndarray:
        """dOCV/dSOC (V per unit SOC) at ``soc``, ``temp_c``."""
        soc, temp_c = np.broadcast_arrays(np.asarray(soc, float), np.asarray(temp_c, float))
        k0, k1, f = self._rows_at(temp_c)
        n = GRID_POINTS - 1
        i0 = np.clip(np.floor(np.clip(soc, 0.0, 1.0) * n).astype(int), 0, n - 1)
        d0 = (self.ocv_v[k0, i0 + 1] - self.ocv_v[k0, i0]) * n
        d1 = (self.ocv_v[k1, i0 + 1] - self.ocv_v[k1, i0]) * n
        lo_ext, hi_ext = self._extrapolation_at(k0, k1, f)
        return np.where(soc < 0.0, lo_ext, np.where(soc > 1.0, hi_ext, d0 + f * (d1 - d0)))

    def soc_from_ocv(self, ocv_v: np.ndarray, temp_c: np.ndarray | float = 25.0) -> np.ndarray:
        """Inverse map: SOC in [0, 1] whose OCV at ``temp_c`` is ``ocv_v``."""
        ocv_v, temp_c = np.broadcast_arrays(np.asarray(ocv_v, float), np.asarray(temp_c, float))
        k0, k1, f = self._rows_at(temp_c)
        rows = self.ocv_v[k0] + f[..., None] * (self.ocv_v[k1] - self.ocv_v[k0])
        grid = np.linspace(0.0, 1.0, GRID_POINTS)
        flat_rows = rows.reshape(-1, GRID_POINTS)
        out = np.array([np.interp(v, r, grid) for v, r in zip(ocv_v.ravel(), flat_rows)])
        return out.reshape(ocv_v.shape)

    @property
    def soc_grid(self) -> np.ndarray:
        return np.linspace(0.0, 1.0, GRID_POINTS)


#: an OCV table's slope below this (V per unit SOC, 0.1 mV per % SOC) counts as flat: a fitted
#: monotone table's step where the data would have had it fall
FLAT_SLOPE_V = 0.01
#: a slope below this (V per unit SOC) is a run the monotone fit held flat: :func:`make_monotone`'s
#: minimum step reads 0.0002, a measured plateau (LFP) ten times this or more. The SOC filter takes
#: little from the voltage on such a run (``EstimatorSettings.flat_ocv_noise_v``)
FLAT_RUN_SLOPE_V = 1e-3


def flat_share(table: OcvTable, temp_c: float) -> float:
    """Share of SOC over which ``table`` at ``temp_c`` rises by less than :data:`FLAT_SLOPE_V`."""
    mid = (np.arange(GRID_POINTS - 1) + 0.5) / (GRID_POINTS - 1)
    return float(np.mean(table.slope(mid, temp_c) < FLAT_SLOPE_V))


def make_monotone(ocv_row: np.ndarray, min_step_v: float = 1e-6) -> np.ndarray:
    """Smallest upward correction that makes a row strictly increasing (running max)."""
    out = np.maximum.accumulate(np.asarray(ocv_row, dtype=float))
    return out + min_step_v * np.arange(out.size)


#: columns accepted as the OCV of an OCV CSV, in order of preference
OCV_COLUMNS = ("ocv_v", "ocv_avg_v", "ocv_discharge_v", "ocv_charge_v")


#: the columns that hold one branch of the OCV (a charge or a discharge test), not the mean
ONE_BRANCH_COLUMNS = {"ocv_charge_v": "charge", "ocv_discharge_v": "discharge"}


def ocv_column(header: list[str]) -> str | None:
    """The OCV column an OCV table's ``header`` gives (the first of :data:`OCV_COLUMNS`), or None."""
    return next((c for c in OCV_COLUMNS if c in header), None)


def ocv_table_branch(path) -> str | None:
    """``charge`` or ``discharge`` where the OCV table at ``path`` holds only that branch's column
    (:data:`ONE_BRANCH_COLUMNS`), else None."""
    import csv
    import io
    from pathlib import Path

    from service.validation import read_text

    header = [h.strip() for h in next(csv.reader(io.StringIO(read_text(Path(path), "OCV table"))), [])]
    col = ocv_column(header)
    return ONE_BRANCH_COLUMNS.get(col) if col is not None else None


#: plausibility of an OCV table's values: SOC as a fraction or in percent, a cell's OCV in volts
#: V: the range a lithium cell's open-circuit voltage lies in
OCV_V_RANGE = (0.0, 6.0)
OCV_BOUNDS: dict[str, tuple[float, float]] = {"soc": (0.0, 100.0), **{c: OCV_V_RANGE for c in OCV_COLUMNS}}


#: V: how far an OCV table may fall as SOC rises (measurement noise on a flat plateau); a larger
#: fall is a reversed column, a wrong column or a corrupt table, which the monotone fit would
#: otherwise flatten into a silently wrong OCV
OCV_MAX_FALL_V = 0.010


def ocv_fall_problem(soc: np.ndarray, ocv_v: np.ndarray) -> str | None:
    """What is wrong where an OCV row falls by more than :data:`OCV_MAX_FALL_V` as SOC rises
    (``soc`` increasing), or None."""
    ocv_v = np.asarray(ocv_v, dtype=float)
    peak = np.maximum.accumulate(ocv_v)
    fall = peak - ocv_v
    k = int(np.argmax(fall))
    if fall[k] <= OCV_MAX_FALL_V:
        return None
    j = int(np.argmax(ocv_v[: k + 1] >= peak[k]))
    return (f"the OCV falls by {1000 * fall[k]:.0f} mV from SOC {soc[j]:g} to {soc[k]:g} "
            f"(more than {1000 * OCV_MAX_FALL_V:.0f} mV): an OCV rises with SOC; is the column reversed or the wrong one?")


#: an OCV table a user gives must span at least this much SOC (the rest would be held flat) ...
OCV_MIN_SOC_SPAN = 0.5
#: ... and rise by at least this much over it (an LFP plateau rises some 40 mV over half its SOC)
OCV_MIN_RISE_V = 0.01


def ocv_span_problem(soc: np.ndarray, ocv_v: np.ndarray) -> str | None:
    """What is wrong where an OCV table (``soc`` increasing) covers too little SOC to read a cell
    by, or does not rise over it (a constant column), or None."""
    if soc[-1] - soc[0] < OCV_MIN_SOC_SPAN:
        return (f"it covers SOC {soc[0]:g} to {soc[-1]:g} only; an OCV table must span at least "
                f"{OCV_MIN_SOC_SPAN:g} of the SOC range (0 to 1 is usual)")
    if (rise := float(np.ptp(ocv_v))) < OCV_MIN_RISE_V:
        return (f"the OCV stays within {1000 * rise:.1f} mV from SOC {soc[0]:g} to {soc[-1]:g}: "
                "an OCV rises with SOC; is it the right column?")
    return None


def load_ocv_csv(path) -> tuple[np.ndarray, np.ndarray]:
    """Read an OCV(SOC) table CSV (``soc`` + one of :data:`OCV_COLUMNS`); blank cells skipped.

    SOC may be in [0, 1] or percent (detected from the maximum).  Raises ``ValueError``
    naming the file and the problem.
    """
    import csv
    import io
    from pathlib import Path

    from service.validation import check_values, header_text, read_text, separator_problem

    path = Path(path)
    rows = list(csv.reader(io.StringIO(read_text(path, "OCV table"))))
    if not rows:
        raise ValueError(f"{path}: empty OCV table")
    header = [h.strip() for h in rows[0]]
    if "soc" not in header and (why := separator_problem(header)) is not None:
        raise ValueError(f"{path}: {why}")
    if "soc" not in header:
        raise ValueError(f"{path}: OCV table needs a 'soc' column; header is {header_text(header)}")
    col = ocv_column(header)
    if col is None:
        raise ValueError(f"{path}: OCV table needs one of columns {', '.join(OCV_COLUMNS)}")
    i_soc, i_ocv = header.index("soc"), header.index(col)
    soc, ocv = [], []
    for n, row in enumerate(rows[1:], start=2):
        if len(row) <= max(i_soc, i_ocv) or not row[i_soc].strip() or not row[i_ocv].strip():
            continue
        for name, i, out in (("soc", i_soc, soc), (col, i_ocv, ocv)):
            try:
                v = float(row[i])
            except ValueError:
                raise ValueError(f"{path}: row {n}: {name}: {row[i].strip()!r} is not a number") from None
            # finite and plausible (SOC as a fraction or in percent; a cell's OCV in volts)
            check_values(path, {name: [v]}, OCV_BOUNDS, first_row=n)
            out.append(v)
    soc_a, ocv_a = np.array(soc), np.array(ocv)
    if soc_a.size < 2:
        raise ValueError(f"{path}: OCV table has fewer than 2 rows with both soc and {col}")
    if soc_a.max() > 1.5:
        soc_a = soc_a / 100.0
    if soc_a.max() > 1.0 + 1e-9:  # a fraction past full (percent above 100 fails the bounds above)
        raise ValueError(f"{path}: soc runs up to {soc_a.max():g}: give it as fractions in [0, 1] or percent "
                         "in [0, 100]")
    order = np.argsort(soc_a)
    soc_a, ocv_a = soc_a[order], ocv_a[order]
    if (np.diff(soc_a) <= 0).any():
        k = int(np.argmax(np.diff(soc_a) <= 0))
        raise ValueError(f"{path}: soc {soc_a[k]:g} appears twice: the table must have one OCV per SOC")
    for problem in (ocv_fall_problem(soc_a, ocv_a), ocv_span_problem(soc_a, ocv_a)):
        if problem is not None:
            raise ValueError(f"{path}: {col}: {problem}")
    return soc_a, ocv_a


class CellOcv:
    """OCV rows of a table evaluated once at each cell's temperature, for fast lookups.

    ``rows[n, s]`` is the cell ``n``'s OCV on the uniform SOC grid; lookups take SOC of
    shape ``[N]`` or ``[N, ...]`` (one leading axis per cell).  ``offset_v[n]`` (optional) is
    added to every row: the entropic shift ``dOCV/dT · (T - T_ref)`` of the temperature
    extension (:class:`service.cell.profile.ArrheniusSpec`).
    """

    def __init__(self, table: OcvTable, temp_c: np.ndarray, offset_v: np.ndarray | None = None) -> None:
        temp_c = np.asarray(temp_c, float)
        k0, k1, f = table._rows_at(temp_c)
        self.rows = table.ocv_v[k0] + f[:, None] * (table.ocv_v[k1] - table.ocv_v[k0])
        if offset_v is not None:
            self.rows = self.rows + np.broadcast_to(np.asarray(offset_v, float), temp_c.shape)[:, None]
        self.steps = np.diff(self.rows, axis=1)  # [N, G-1]
        self._rows_flat = self.rows.ravel()
        self._steps_flat = self.steps.ravel()
        self._row_offset = (np.arange(self.rows.shape[0]) * GRID_POINTS)[:, None]
        lo_ext, hi_ext = table._extrapolation_at(k0, k1, f)
        self._lo_ext, self._hi_ext = lo_ext[:, None], hi_ext[:, None]
        self._step_offset = (np.arange(self.rows.shape[0]) * (GRID_POINTS - 1))[:, None]

    def _index(self, soc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = GRID_POINTS - 1
        flat = soc.reshape(soc.shape[0], -1)
        # fmin/fmax map NaN into the table (the caller's divergence check handles NaN) at a
        # fraction of nan_to_num's cost: this runs three times per filter step
        x = np.fmax(np.fmin(flat, 1.0), 0.0) * n
        i0 = np.minimum(x.astype(int), n - 1)
        return flat, i0, x - i0

    def ocv(self, soc: np.ndarray) -> np.ndarray:
        return self._ocv(soc, *self._index(soc))

    def slope(self, soc: np.ndarray) -> np.ndarray:
        return self._slope(soc, *self._index(soc))

    def on_flat_run(self, soc: np.ndarray) -> np.ndarray:
        """Whether each ``soc`` sits on a run of the table held flat (:data:`FLAT_RUN_SLOPE_V`)."""
        return self.slope(soc) < FLAT_RUN_SLOPE_V

    def ocv_and_slope(self, soc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(ocv(soc), slope(soc))`` from one table lookup (the identifiers need both each step)."""
        idx = self._index(soc)
        return self._ocv(soc, *idx), self._slope(soc, *idx)

    def _ocv(self, soc: np.ndarray, flat: np.ndarray, i0: np.ndarray, u: np.ndarray) -> np.ndarray:
        v = self._rows_flat[i0 + self._row_offset] + u * self._steps_flat[i0 + self._step_offset]
        v = v + self._lo_ext * np.minimum(flat, 0.0) + self._hi_ext * np.maximum(flat - 1.0, 0.0)
        return v.reshape(soc.shape)

    def _slope(self, soc: np.ndarray, flat: np.ndarray, i0: np.ndarray, u: np.ndarray) -> np.ndarray:
        d = self._steps_flat[i0 + self._step_offset] * (GRID_POINTS - 1)
        d = np.where(flat < 0.0, self._lo_ext, np.where(flat > 1.0, self._hi_ext, d))
        return d.reshape(soc.shape)
