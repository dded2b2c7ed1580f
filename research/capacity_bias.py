"""Where a recording's voltage puts the SOC when the capacity is right: the evidence the online
capacity estimator reads, band by band of true SOC.

``python -m research.capacity_bias RECORDING [--cell PROFILE] [--soc0 1.0] [--json OUT]``

Two runs of the paper's pipeline for one cell (:class:`service.estimators.pipeline.PackEstimator`),
both started at the true SOC:

- **frozen** (``capacity_estimation = "off"``): the filter counts charge with the profile's
  capacity, which is the truth's.  In each band of true SOC its voltage innovations ``e`` are read
  as an SOC offset, the least-squares ``Σ e·s / Σ s²`` with ``s = dOCV/dSOC`` at the filter's SOC:
  how far below (negative) or above the coulomb count the profile's model places the cell from
  its voltage.  This is what the capacity estimator's measurement ``H = dOCV/dSOC · dSOC/dφ``
  integrates (:mod:`service.estimators.capacity`); with a model consistent with the cell it is
  zero up to noise.
- **absolute** (``capacity_estimation = "absolute"``): the capacity the dual EKF has learned by
  the end of each band, as an error against the profile's (the truth's) capacity.

Truth: the recording's ``soc_true`` where present, else coulomb counting from ``--soc0`` with the
profile's capacity (DESIGN §7).  docs/results/bench.md runs it on the demo's recorded drive and
on the same drive through the profile's own model (:mod:`research.model_drive`).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from service.cell.coulomb import coulomb_soc
from service.cell.memory import sample_period_s
from service.cell.profile import CellProfile, ProfileError, load_profile
from service.config import DEFAULT_CELL_PROFILE
from service.errors import UserError
from service.estimators.pipeline import PackEstimator
from service.estimators.settings import EstimatorSettings
from service.recording import Recording, load_recording

BAND_WIDTH = 0.1


@dataclass
class Band:
    """One band of true SOC along the drive."""

    soc_from_pct: float
    soc_to_pct: float
    samples: int
    voltage_soc_offset_pct: float  # least-squares SOC offset the frozen filter's innovations point to
    frozen_soc_error_pct: float  # the frozen filter's mean SOC error in the band
    absolute_capacity_err_pct: float  # the absolute dual EKF's capacity error at the band's last sample


@dataclass
class CapacityBias:
    recording: str
    profile: str
    capacity_ah: float
    bands: list[Band]
    voltage_soc_offset_pct: float  # over the whole drive after the first band
    absolute_capacity_err_pct: float  # at the end of the drive


def _run(profile: CellProfile, rec: Recording, soc0: float, mode: str) -> tuple[np.ndarray, ...]:
    """``(soc, innovation, ocv slope, capacity error %)`` per sample of one pipeline run."""
    settings = EstimatorSettings().model_copy(update={"capacity_estimation": mode})
    est = PackEstimator(profile, 1, settings, "multi", sample_period_s(rec.time_s))
    est.start(np.array([soc0]))
    n = len(rec)
    soc, innov, slope, cap = (np.empty(n) for _ in range(4))
    dt = rec.dt_s()
    one = np.ones(1, dtype=bool)
    q = profile.effective_capacity_ah
    for k in range(n):
        est.step(dt[k], rec.current_a[k], rec.voltage_v[k:k + 1], rec.temperature_c[k:k + 1], one)
        est.slow_update()
        soc[k], innov[k] = est.soc[0], est.ukf.innovation[0]
        slope[k] = est.cell_ocv.slope(est.soc)[0]
        cap[k] = 100.0 * (est.capacity_ah[0] / q - 1.0)
    return soc, innov, slope, cap


def _offset_pct(innov: np.ndarray, slope: np.ndarray) -> float:
    den = float(np.sum(slope * slope))
    return 100.0 * float(np.sum(innov * slope)) / den if den > 0 else float("nan")


def capacity_bias(recording: Path, profile_path: Path, soc0: float) -> CapacityBias:
    """The two runs of the module docstring, summarised per band of true SOC."""
    profile = load_profile(profile_path)
    rec = load_recording(recording)
    q = profile.effective_capacity_ah
    truth = rec.soc_true if rec.soc_true is not None else coulomb_soc(rec.time_s, rec.current_a, q, soc0)
    soc, innov, slope, _ = _run(profile, rec, soc0, "off")
    *_, cap = _run(profile, rec, soc0, "absolute")
    edges = np.arange(0.0, 1.0 + BAND_WIDTH / 2, BAND_WIDTH)
    band_of = np.clip(np.digitize(truth, edges) - 1, 0, len(edges) - 2)
    bands = []
    for b in range(len(edges) - 2, -1, -1):  # a discharge visits the bands from the top
        idx = np.flatnonzero(band_of == b)
        if idx.size < 10:
            continue
        bands.append(Band(100 * edges[b], 100 * edges[b + 1], int(idx.size),
                          _offset_pct(innov[idx], slope[idx]),
                          100.0 * float(np.mean(soc[idx] - truth[idx])), float(cap[idx[-1]])))
    after_first = band_of < band_of[0]
    return CapacityBias(recording.name, profile_path.name, q, bands,
                        _offset_pct(innov[after_first], slope[after_first]), float(cap[-1]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.capacity_bias", description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", help="recording CSV (a soc_true column is used as the truth)")
    ap.add_argument("--cell", default=str(DEFAULT_CELL_PROFILE), help="cell profile (default: the bundled one)")
    ap.add_argument("--soc0", type=float, default=1.0, help="true SOC at the first sample (default 1.0)")
    ap.add_argument("--json", help="write the bands as JSON here")
    args = ap.parse_args(argv)
    if not 0.0 <= args.soc0 <= 1.0:
        print("capacity_bias: --soc0 must be in [0, 1]", file=sys.stderr)
        return 2
    try:
        result = capacity_bias(Path(args.recording), Path(args.cell), args.soc0)
    except (ProfileError, UserError, ValueError, OSError) as exc:
        print(f"capacity_bias: {exc}", file=sys.stderr)
        return 2
    for b in result.bands:
        print(f"SOC {b.soc_from_pct:3.0f}-{b.soc_to_pct:3.0f} %: voltage says {b.voltage_soc_offset_pct:+6.2f} % SOC, "
              f"frozen filter {b.frozen_soc_error_pct:+5.2f} %, absolute capacity {b.absolute_capacity_err_pct:+5.2f} %")
    print(f"whole drive: voltage says {result.voltage_soc_offset_pct:+.2f} % SOC; "
          f"absolute capacity at the end {result.absolute_capacity_err_pct:+.2f} %")
    if args.json:
        Path(args.json).write_text(json.dumps(asdict(result), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
