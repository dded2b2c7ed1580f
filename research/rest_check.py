"""Does a recording's truth agree with the cell's OCV table?  Checked at the ends of its rests.

``socd evaluate`` scores SOC against a truth: ``soc_true``, or coulomb counting from a full
point with the profile's capacity.  Where that truth is off (the full point was not full, the
capacity has faded, the counter drifts), every estimator that reads the voltage is scored as
wrong by the same amount.  At the end of a long rest the voltage is close to the OCV, so the
OCV table gives SOC independently of the truth::

    SOC_ocv = OCV⁻¹(V_end − U_h, T_end)

with ``U_h = −sign(I_last)·U_H`` the profile's hysteresis fully developed on the branch of the
last current before the rest (Zeng Eq. 1; 0 for a profile without hysteresis).  The difference
``SOC_ocv − truth`` is reported with how much the voltage still moves at the rest's end
(``tail_mv_per_min``, a line through its last minute, or its last three samples where the log is
sparser): a rest that has not relaxed reads too low
after a discharge (too high after a charge), by more the colder and emptier the cell.  So compare
rests of the same length at similar SOC and temperature, and read the sign of the tail.

    python -m research.rest_check --cell configs/cells/panasonic_18650pf.toml \\
        ../shared/data/real/panasonic_18650pf/pan18650pf_10C_trise_Cycle1.csv
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from service.cell.fitting import last_current_direction
from service.cell.profile import CellProfile, ProfileError, load_profile
from service.cell.rests import rest_level_a
from service.cell.truth import per_recording, truth_and_start
from service.characterisation.ocv_sources import rest_spans
from service.errors import UserError
from service.recording import Recording, load_recording

#: shortest rest read (s): the Panasonic drive cycles end with 300 s
DEFAULT_MIN_REST_S = 240.0
#: the rest's last stretch the tail slope is fitted over (s)
TAIL_S = 60.0


@dataclass
class RestReading:
    recording: str
    t_s: float  # end of the rest, from the start of the scored part
    rest_s: float
    voltage_v: float
    temperature_c: float
    u_h_v: float
    soc_ocv: float
    soc_true: float
    diff_pct: float  # (SOC_ocv - truth) x 100
    tail_mv_per_min: float | None  # None: fewer than three samples in the rest


def read_rests(part: Recording, truth: np.ndarray, profile: CellProfile,
               min_rest_s: float = DEFAULT_MIN_REST_S) -> list[RestReading]:
    """One reading at the end of every rest of at least ``min_rest_s`` in ``part``."""
    capacity = profile.effective_capacity_ah
    table = profile.ocv_table()
    u_h_max = float(profile.hysteresis.u_h_max_v)
    rest_a = rest_level_a(part.current_a, capacity)
    out = []
    for first, last in rest_spans(part, capacity, min_rest_s):
        u_h = last_current_direction(part.current_a[:first], rest_a) * u_h_max
        v, temp = float(part.voltage_v[last]), float(part.temperature_c[last])
        soc_ocv = float(table.soc_from_ocv(np.array([v - u_h]), np.array([temp]))[0])
        t_rest, v_rest = part.time_s[first:last + 1], part.voltage_v[first:last + 1]
        k0 = min(int(np.searchsorted(t_rest, t_rest[-1] - TAIL_S)), max(t_rest.size - 3, 0))
        t_tail, v_tail = t_rest[k0:], v_rest[k0:]  # the last minute, or 3 samples of a sparse log
        slope = float(np.polyfit(t_tail - t_tail[0], v_tail, 1)[0]) if t_tail.size >= 3 else None
        out.append(RestReading(
            recording=part.name, t_s=float(part.time_s[last] - part.time_s[0]),
            rest_s=float(part.time_s[last] - part.time_s[first]), voltage_v=v, temperature_c=temp,
            u_h_v=u_h, soc_ocv=soc_ocv, soc_true=float(truth[last]),
            diff_pct=100.0 * (soc_ocv - float(truth[last])),
            tail_mv_per_min=None if slope is None else 60e3 * slope,
        ))
    return out


def markdown(readings: list[RestReading]) -> str:
    out = ["| recording | rest end, s | rest, s | V | T, °C | SOC by OCV | truth | OCV − truth, % | tail, mV/min |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in readings:
        out.append(f"| {r.recording} | {r.t_s:.0f} | {r.rest_s:.0f} | {r.voltage_v:.4f} | {r.temperature_c:.1f} | "
                   f"{r.soc_ocv:.3f} | {r.soc_true:.3f} | {r.diff_pct:+.2f} | "
                   + ("–" if r.tail_mv_per_min is None else f"{r.tail_mv_per_min:+.2f}") + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m research.rest_check",
        description="At the end of every long rest, compare the SOC the profile's OCV table reads from the "
                    "voltage with the truth 'socd evaluate' scores against (soc_true, or coulomb counting from "
                    "--full-at with the profile's capacity). A difference common to every estimator's error "
                    "points at the truth or the OCV table, not the estimator.",
    )
    p.add_argument("recordings", nargs="+", metavar="RECORDING", help="CSV as for socd evaluate")
    p.add_argument("--cell", required=True, help="cell profile (TOML/JSON) whose OCV table and capacity are used")
    p.add_argument("--full-at", action="append", metavar="SECONDS",
                   help="full-charge point as for socd evaluate (once for all, or once per recording)")
    p.add_argument("--min-rest-s", type=float, default=DEFAULT_MIN_REST_S,
                   help=f"shortest rest read, s (default {DEFAULT_MIN_REST_S:g})")
    p.add_argument("--json", metavar="OUT", help="write the readings as JSON")
    args = p.parse_args(argv)
    try:
        if not args.min_rest_s > TAIL_S:
            raise UserError(f"--min-rest-s must be above {TAIL_S:g} s (the tail is fitted over the last "
                            f"{TAIL_S:g} s), got {args.min_rest_s:g}")
        try:
            profile = load_profile(args.cell)
        except ProfileError as exc:
            raise UserError(str(exc)) from exc
        full = per_recording(args.full_at, len(args.recordings), "--full-at")
        recordings = [load_recording(r) for r in args.recordings]
        capacity = profile.effective_capacity_ah
        readings: list[RestReading] = []
        for rec, fa in zip(recordings, full):
            part, truth = truth_and_start(rec, capacity, fa)
            found = read_rests(part, truth, profile, args.min_rest_s)
            if not found:
                print(f"rest_check: {rec.path}: no rest of {args.min_rest_s:g} s or more", file=sys.stderr)
            readings += found
    except UserError as exc:
        print(f"rest_check: error: {exc}", file=sys.stderr)
        return 2
    print(markdown(readings))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"cell": args.cell, "min_rest_s": args.min_rest_s,
                                               "rests": [asdict(r) for r in readings]}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
