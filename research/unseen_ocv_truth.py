"""How far ``socd fit``'s reading of an OCV test is from the cell's own OCV, on research.unseen_cell's
PyBaMM cells, where the true OCV is known.

``python -m research.unseen_ocv_truth [--cells ...] [--ambients 25,10,0] [--json OUT]`` reads each
cell's OCV test (built by ``research.unseen_cell build``) both ways :func:`ocv_from_test` can
(each branch on its own throughput, the default; ``short_charge``) and compares each curve with
PyBaMM's bulk open-circuit voltage along a C/20 discharge of the same cell at the same ambient
(SOC counted over that discharge's capacity, as the test's SOC is).  It prints the RMS difference,
mV, in bands of SOC, and where the test's charge stopped (``charge_reach``).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from research.unseen_cell import CELLS, DEFAULT_WORKDIR, _temp_tag, c20_solution
from service.characterisation.ocv_sources import ocv_from_test
from service.recording import load_recording

#: SOC bands the difference is reported in
BANDS = ((0.05, 0.5), (0.5, 0.8), (0.8, 0.9), (0.9, 0.95), (0.95, 0.99), (0.99, 1.0))


@dataclass
class OcvTruthRow:
    cell: str
    ambient_c: float
    charge_reach: float
    #: RMS difference from the bulk OCV per band of :data:`BANDS`, mV: each branch on its own scale
    stretched_mv: list[float]
    #: the same with ``short_charge``
    short_charge_mv: list[float]
    #: mean SOC the default (stretched) curve reads at the bulk OCV, minus the true SOC, per band, %:
    #: the sign and size of what an estimator inherits from the table (positive: reads high)
    stretched_soc_pct: list[float] = field(default_factory=list)


def bulk_ocv(cell: str, ambient_c: float) -> tuple[np.ndarray, np.ndarray]:
    """``(soc, ocv_v)`` of PyBaMM's bulk open-circuit voltage along the OCV test's C/20 discharge
    (:func:`research.unseen_cell.c20_solution`), SOC ascending."""
    sol = c20_solution(cell, ambient_c, charge=False)
    q = sol["Discharge capacity [A.h]"].entries
    soc = 1.0 - q / q.max()
    return soc[::-1], sol["Bulk open-circuit voltage [V]"].entries[::-1]


def band_rms_mv(grid: np.ndarray, error_v: np.ndarray) -> list[float]:
    """RMS of ``error_v`` in each band of :data:`BANDS` (the last band closed at 1), mV."""
    out = []
    for lo, hi in BANDS:
        inside = (grid >= lo) & ((grid < hi) if hi < 1.0 else (grid <= hi))
        out.append(round(float(np.sqrt(np.mean(error_v[inside] ** 2))) * 1e3, 1))
    return out


def band_mean_pct(grid: np.ndarray, soc_error: np.ndarray) -> list[float]:
    """Mean of ``soc_error`` (a fraction) in each band of :data:`BANDS`, %."""
    out = []
    for lo, hi in BANDS:
        inside = (grid >= lo) & ((grid < hi) if hi < 1.0 else (grid <= hi))
        out.append(round(100.0 * float(np.mean(soc_error[inside])), 2))
    return out


def soc_read_error(grid: np.ndarray, table_v: np.ndarray, truth_v: np.ndarray) -> np.ndarray:
    """The SOC a table ``(grid, table_v)`` reads at the cell's own OCV ``truth_v`` on the same grid,
    minus the grid (the true SOC); the table is read as the estimators read it, by inverse
    interpolation, flat stretches at their first SOC."""
    rising, first = np.unique(table_v, return_index=True)
    return np.interp(truth_v, rising, grid[first]) - grid


def compare(cell: str, ambient_c: float, workdir: Path) -> OcvTruthRow:
    stem = f"{cell}_{_temp_tag(ambient_c)}_ocv"
    capacity = json.loads((workdir / f"{stem}.json").read_text())["capacity_ah"]
    rec = load_recording(workdir / f"{stem}.csv")
    soc, ocv = bulk_ocv(cell, ambient_c)
    stretched = ocv_from_test(rec, capacity)
    short = ocv_from_test(rec, capacity, short_charge=True)
    truth = np.interp(stretched.grid, soc, ocv)
    return OcvTruthRow(cell, ambient_c, round(stretched.charge_reach, 4),
                       band_rms_mv(stretched.grid, stretched.ocv_v - truth),
                       band_rms_mv(short.grid, short.ocv_v - truth),
                       band_mean_pct(stretched.grid, soc_read_error(stretched.grid, stretched.ocv_v, truth)))


def markdown(rows: list[OcvTruthRow]) -> str:
    bands = " | ".join(f"{lo:g}-{hi:g}" for lo, hi in BANDS)
    lines = [f"| cell | ambient | charge reached | read | {bands} |",
             "|---|---|---|---|" + "---|" * len(BANDS)]
    for r in rows:
        for label, mv in (("stretched (default)", r.stretched_mv), ("`--short-charge`", r.short_charge_mv)):
            lines.append(f"| `{r.cell}` | {r.ambient_c:g} °C | {100 * r.charge_reach:.1f} % | {label} | "
                         + " | ".join(f"{x:.1f}" for x in mv) + " |")
    read = [r for r in rows if r.stretched_soc_pct]
    if read:
        title = ("SOC the default curve reads at the cell's own OCV, minus the true SOC, mean per band (%; "
                 "positive: reads high):")
        lines += ["", title, "", f"| cell | ambient | {bands} |", "|---|---|" + "---|" * len(BANDS)]
        lines += [f"| `{r.cell}` | {r.ambient_c:g} °C | " + " | ".join(f"{x:+.2f}" for x in r.stretched_soc_pct) + " |"
                  for r in read]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.unseen_ocv_truth", description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", default=",".join(CELLS), help=f"PyBaMM parameter sets (default {','.join(CELLS)})")
    ap.add_argument("--ambients", default="25,10,0", help="ambient temperatures, °C (default 25,10,0)")
    ap.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR, help=f"default {DEFAULT_WORKDIR}")
    ap.add_argument("--json", type=Path, help="write the rows as JSON")
    a = ap.parse_args(argv)
    rows = [compare(c, float(t), a.workdir) for c in a.cells.split(",") if c for t in a.ambients.split(",") if t]
    print(markdown(rows))
    if a.json:
        a.json.write_text(json.dumps([asdict(r) for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
