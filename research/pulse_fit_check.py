"""How a profile reproduces the pulse test it was fitted on: by SOC, and pulse by pulse.

``python -m research.pulse_fit_check PROFILE RECORDING... --capacity-ah X [--json OUT]`` splits each
recording (a pulse test that starts full, e.g. ``pan18650pf_10C_HPPC.csv``) at its rests as
``socd fit`` does (:func:`service.characterisation.characterise.split_at_rests`), simulates every
segment with the profile from its relaxed start (:func:`service.cell.trajectory.simulate`), and
reports:

* the mean residual (model − measured) under load in three SOC bands of the segment's start
  (below 0.2, 0.2-0.8, 0.8 and above): a positive value is a model that polarises too little;
* for pulses from rest, the apparent resistance ΔV/ΔI 1 s and 10 s after the step, measured and
  simulated, by C-rate (the pulse levels rounded to one significant figure).

A fit whose resistances are flat in SOC is a compromise between the SOC ends, where a pulse test
polarises the cell most, and the middle, where drive cycles spend their time; this shows which way
it went (docs/results/characterisation.md, hppc_pulse_check).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from dataclasses import asdict, dataclass, field

import numpy as np

#: SOC bands of a segment's start (lower edges), named for the table
SOC_BANDS = ((0.0, "SOC < 0.2"), (0.2, "0.2-0.8"), (0.8, "SOC ≥ 0.8"))
#: times after a step from rest at which the apparent resistance is read, s
PULSE_READ_S = (1.0, 10.0)
#: a pulse is read only where a sample lies within this factor of the read time after the step
PULSE_READ_SLACK = 1.5
#: a pulse is read only while its current stays within this share of its level
PULSE_STEADY = 0.1


@dataclass
class PulseReading:
    c_rate: float
    after_s: float
    measured_mohm: float
    model_mohm: float


@dataclass
class RecordingCheck:
    recording: str
    median_temp_c: float
    load_residual_mv: dict[str, float] = field(default_factory=dict)
    load_segments: dict[str, int] = field(default_factory=dict)
    pulses: list[PulseReading] = field(default_factory=list)


def band_of(soc0: float) -> str:
    return [name for lo, name in SOC_BANDS if soc0 >= lo][-1]


def pulse_readings(time_s, current_a, voltage_v, model_v, rest_a: float, capacity_ah: float) -> list[PulseReading]:
    """Apparent resistances of the steps from rest in one segment (module docstring)."""
    out = []
    steps = np.where((np.abs(current_a[:-1]) <= rest_a) & (np.abs(current_a[1:]) > 4.0 * rest_a))[0]
    for j in steps:
        level = float(current_a[j + 1])
        for after in PULSE_READ_S:
            k = int(np.searchsorted(time_s, time_s[j] + after - 1e-6))
            if k >= time_s.size or k <= j or np.ptp(current_a[j + 1:k + 1]) > PULSE_STEADY * abs(level):
                continue
            if time_s[k] - time_s[j] > PULSE_READ_SLACK * after:  # no sample near the read time
                continue
            c = level / capacity_ah
            c_rounded = float(f"{c:.1g}")
            out.append(PulseReading(c_rounded, after, -1e3 * (voltage_v[k] - voltage_v[j]) / level,
                                    -1e3 * (model_v[k] - model_v[j]) / level))
    return out


def check_recording(profile, path: str, capacity_ah: float) -> RecordingCheck:
    from service.cell.coulomb import coulomb_soc
    from service.cell.rests import load_level_a, rest_level_a
    from service.cell.trajectory import simulate
    from service.characterisation.characterise import split_at_rests
    from service.recording import load_recording

    rec = load_recording(path)
    soc = coulomb_soc(rec.time_s, rec.current_a, capacity_ah, 1.0)
    rest_a, load_a = rest_level_a(rec.current_a, capacity_ah), load_level_a(rec.current_a, capacity_ah)
    check = RecordingCheck(path.rsplit("/", 1)[-1], float(np.median(rec.temperature_c)))
    by_band: dict[str, list[float]] = {name: [] for _, name in SOC_BANDS}
    for seg in split_at_rests(rec, soc, capacity_ah):
        model_v, _ = simulate(profile, seg.time_s, seg.current_a, seg.temperature_c, seg.soc0)
        load = np.abs(seg.current_a) > load_a
        if load.any():
            by_band[band_of(seg.soc0)].append(1e3 * float(np.mean((model_v - seg.voltage_v)[load])))
        check.pulses += pulse_readings(seg.time_s, seg.current_a, seg.voltage_v, model_v, rest_a, capacity_ah)
    check.load_residual_mv = {k: statistics.fmean(v) for k, v in by_band.items() if v}
    check.load_segments = {k: len(v) for k, v in by_band.items() if v}
    return check


def pulse_summary(check: RecordingCheck) -> list[tuple[float, float, float, float, int]]:
    """``(C-rate, after_s, median measured, median model, pulses)`` per pulse level and read time
    (discharge pulses)."""
    keys = sorted({(p.c_rate, p.after_s) for p in check.pulses if p.c_rate > 0})
    rows = []
    for c, after in keys:
        sel = [p for p in check.pulses if p.c_rate == c and p.after_s == after]
        rows.append((c, after, statistics.median(p.measured_mohm for p in sel),
                     statistics.median(p.model_mohm for p in sel), len(sel)))
    return rows


def read_json(path: str) -> list[RecordingCheck]:
    """The checks ``--json`` wrote."""
    with open(path) as fh:
        rows = json.load(fh)
    return [RecordingCheck(**{**r, "pulses": [PulseReading(**p) for p in r["pulses"]]}) for r in rows]


def table(checks: list[RecordingCheck]) -> str:
    """Two markdown tables: residual under load by SOC band; pulse resistances by C-rate at 1 s."""
    bands = [name for _, name in SOC_BANDS]
    lines = ["| recording | median T, °C | " + " | ".join(f"mean residual under load, {b} [mV]" for b in bands) + " |",
             "|---|---|" + "---|" * len(bands)]
    for ch in checks:
        cells = [f"{ch.load_residual_mv[b]:+.0f} ({ch.load_segments[b]})" if b in ch.load_residual_mv else "-"
                 for b in bands]
        lines.append(f"| {ch.recording} | {ch.median_temp_c:.1f} | " + " | ".join(cells) + " |")
    summaries = [pulse_summary(ch) for ch in checks]
    rates = sorted({c for summ in summaries for c, *_ in summ})
    lines += ["", "| recording | read after | " + " | ".join(f"{c:g}C measured / model [mΩ]" for c in rates) + " |",
              "|---|---|" + "---|" * len(rates)]
    for ch, summ in zip(checks, summaries):
        for after in PULSE_READ_S:
            by_c = {c: (m, s) for c, a, m, s, _ in summ if a == after}
            cells = [f"{by_c[c][0]:.0f} / {by_c[c][1]:.0f}" if c in by_c else "-" for c in rates]
            lines.append(f"| {ch.recording} | {after:g} s | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.pulse_fit_check", description=__doc__.split("\n\n")[0])
    ap.add_argument("profile", help="cell profile (TOML/JSON)")
    ap.add_argument("recordings", nargs="+", help="pulse tests that start full (CSV)")
    ap.add_argument("--capacity-ah", type=float, required=True, help="cell capacity [Ah]")
    ap.add_argument("--json", help="write the readings here")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.capacity_ah) and args.capacity_ah > 0):
        print(f"error: --capacity-ah {args.capacity_ah} must be a positive number", file=sys.stderr)
        return 2
    from service.cell.profile import ProfileError, load_profile
    from service.errors import UserError

    try:
        profile = load_profile(args.profile)
        checks = [check_recording(profile, p, args.capacity_ah) for p in args.recordings]
    except (ProfileError, UserError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(table(checks))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump([asdict(c) for c in checks], fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
