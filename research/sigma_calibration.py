"""Choose the published SOC σ's considered errors leave-one-cell-out (research tooling).

The SOC the pipeline publishes does not depend on ``reported_ocv_error_v`` and
``reported_current_offset_c`` (``service/estimators/consider.py``); only its σ does. So each
recording is run once, with ``socd evaluate``'s ``fomiukf`` and a wrong start as DESIGN §7
has it, and every grid value's σ is propagated beside it on the same gains (one value per
"cell" of a :class:`ConsiderCovariance`).

Each value is scored by the continuous ranked probability score of the published estimate
(a Gaussian of that σ) against the truth after 600 s: a proper score in SOC units that
rewards a σ that covers the errors and is no wider than it must be, and is not ruled by a
few samples far outside it as the log score is. The value for a held-out cell is the one
with the lowest mean score over the other cells (each cell weighted equally, its recordings
and current-offset conditions pooled); the default is the one chosen on every cell.

    python -m research.sigma_calibration --bias 0 --bias 0.01 --jobs 2 --json out/sigma.json \\
        calce=out/s25/calce.toml:REC.csv@10015 a123=out/s25/a123.toml:REC.csv@4478 ...
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import statistics
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.special import erf

from service.cell.profile import load_profile
from service.cell.truth import truth_and_start
from service.estimators.consider import MAX_REPORTED_SOC_STD, ConsiderCovariance
from service.estimators.pipeline import PackEstimator, fomiukf, sample_period_s
from service.estimators.settings import EstimatorSettings
from service.evaluation.metrics import within_2sigma_pct
from service.evaluation.run import wrong_start
from service.recording import load_recording

OCV_ERROR_GRID_V = (0.0, 0.005, 0.01, 0.02, 0.03, 0.05)
CURRENT_OFFSET_GRID_C = (0.0, 0.005, 0.01, 0.02)
SCORED_AFTER_S = 600.0


@dataclass(frozen=True)
class Spec:
    cell: str
    profile: str
    recording: str
    full_at: str | None


@dataclass
class Score:
    cell: str
    recording: str
    bias_c: float
    ocv_error_v: float
    current_offset_c: float
    crps_pct: float
    within_2sigma_pct: float
    median_sigma_pct: float
    soc_rmse_pct: float


def parse_spec(text: str) -> Spec:
    """``CELL=PROFILE:RECORDING[@FULL_AT]``."""
    try:
        cell, rest = text.split("=", 1)
        profile, rec = rest.split(":", 1)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not CELL=PROFILE:RECORDING[@FULL_AT]") from None
    rec, _, full_at = rec.partition("@")
    return Spec(cell, profile, rec, full_at or None)


def crps_gaussian(err: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """CRPS of N(0, σ²) at ``err``, in closed form (Gneiting & Raftery 2007)."""
    z = err / sigma
    pdf = np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
    cdf = 0.5 * (1 + erf(z / math.sqrt(2)))
    return sigma * (z * (2 * cdf - 1) + 2 * pdf - 1 / math.sqrt(math.pi))


def score_recording(job: tuple[Spec, float]) -> list[Score]:
    """Run ``fomiukf`` once on one recording under one current offset; score every grid value."""
    spec, bias_c = job
    profile = load_profile(spec.profile)
    part, truth = truth_and_start(load_recording(spec.recording), profile.effective_capacity_ah, spec.full_at)
    current = part.current_a + bias_c * profile.effective_capacity_ah
    grid = list(itertools.product(OCV_ERROR_GRID_V, CURRENT_OFFSET_GRID_C))
    pipeline = fomiukf()
    est = PackEstimator(profile, 1, pipeline.settings, pipeline.identification, sample_period_s(part.time_s))
    est.start(np.array([wrong_start(float(truth[0]), 0.20)]))
    considered = ConsiderCovariance(len(grid), [g[0] for g in grid], [g[1] for g in grid],
                                    pipeline.settings.ocv_error_soc_length)
    T, one, dt = len(part), np.ones(1, dtype=bool), part.dt_s()
    soc, var = np.empty(T), np.empty((T, len(grid)))
    for k in range(T):
        est.step(dt[k], current[k], part.voltage_v[k:k + 1], part.temperature_c[k:k + 1], one)
        est.slow_update()
        considered.step(dt[k], *(np.broadcast_to(x, (len(grid),)) for x in est.consider_inputs(one)))
        soc[k] = est.soc[0]
        var[k] = est.filter_soc_std[0] ** 2 + considered.soc_var
    after = part.time_s - part.time_s[0] >= SCORED_AFTER_S
    err, sigma = (soc - truth)[after], np.sqrt(np.minimum(var[after], MAX_REPORTED_SOC_STD**2))
    rmse = 100 * float(np.sqrt(np.mean(err**2)))
    name = Path(spec.recording).stem
    return [Score(spec.cell, name, bias_c, o, b, 100 * float(np.mean(crps_gaussian(err, sigma[:, g]))),
                  within_2sigma_pct(100 * err, sigma[:, g]), 100 * float(np.median(sigma[:, g])), rmse)
            for g, (o, b) in enumerate(grid)]


def _value(s: Score) -> tuple[float, float]:
    return s.ocv_error_v, s.current_offset_c


def cell_means(scores: list[Score], field: str) -> dict[str, dict[tuple[float, float], float]]:
    """Per cell and grid value, the mean of ``field`` over its recordings and conditions."""
    out: dict[str, dict[tuple[float, float], list[float]]] = {}
    for s in scores:
        out.setdefault(s.cell, {}).setdefault(_value(s), []).append(getattr(s, field))
    return {c: {v: statistics.fmean(x) for v, x in d.items()} for c, d in out.items()}


def choose(crps: dict[str, dict[tuple[float, float], float]], cells: list[str]) -> tuple[float, float]:
    values = next(iter(crps.values())).keys()
    return min(values, key=lambda v: statistics.fmean(crps[c][v] for c in cells))


def shipped_lines(crps: dict, cover: dict, sigma: dict) -> list[str]:
    """Each cell at the values ``EstimatorSettings()`` ships, beside the filter's own σ."""
    s = EstimatorSettings()
    v, off = (s.reported_ocv_error_v, s.reported_current_offset_c), (0.0, 0.0)
    cells = sorted(crps)
    if any(v not in crps[c] for c in cells):
        return [f"The shipped values ({v[0]:g} V, {v[1]:g} C) are not on the grid."]
    lines = [f"Each cell at the shipped values ({v[0]:g} V, {v[1]:g} C):", "",
             "| cell | in 2σ, % | median σ, % | CRPS, % | filter's own σ: in 2σ, % | CRPS, % |", "|---|---|---|---|---|---|"]
    lines += [f"| {c} | {cover[c][v]:.1f} | {sigma[c][v]:.2f} | {crps[c][v]:.3f} | {cover[c][off]:.1f} "
              f"| {crps[c][off]:.3f} |" for c in cells]
    return lines


def report(scores: list[Score]) -> tuple[list[str], dict]:
    crps, cover, sigma = (cell_means(scores, f) for f in ("crps_pct", "within_2sigma_pct", "median_sigma_pct"))
    cells = sorted(crps)
    off = (0.0, 0.0)
    header = ("| held-out cell | chosen on the other cells (V, C) | in 2σ, % | median σ, % | CRPS, % "
              "| filter's own σ: in 2σ, % | median σ, % | CRPS, % |")
    lines = [header, "|---|---|---|---|---|---|---|---|"]
    held = {}
    for c in cells:
        v = choose(crps, [o for o in cells if o != c])
        held[c] = v
        lines.append(f"| {c} | {v[0]:g} V, {v[1]:g} C | {cover[c][v]:.1f} | {sigma[c][v]:.2f} | {crps[c][v]:.3f} "
                     f"| {cover[c][off]:.1f} | {sigma[c][off]:.2f} | {crps[c][off]:.3f} |")
    default = choose(crps, cells)
    chosen = (f"Chosen on every cell here: `reported_ocv_error_v = {default[0]:g}`, "
              f"`reported_current_offset_c = {default[1]:g}`.")
    lines += ["", chosen, "", *shipped_lines(crps, cover, sigma), "",
              "Each cell at every grid value (in 2σ % / CRPS %):", "",
              "| OCV error, V | offset, C | " + " | ".join(cells) + " |", "|---|---|" + "---|" * len(cells)]
    for v in sorted(crps[cells[0]]):
        lines.append(f"| {v[0]:g} | {v[1]:g} | " + " | ".join(f"{cover[c][v]:.1f} / {crps[c][v]:.3f}" for c in cells) + " |")
    return lines, {"held_out": {c: list(v) for c, v in held.items()}, "default": list(default)}


def markdown(json_path: Path) -> str:
    """The report again from a ``--json`` file (docs/results/regenerate.py renders it so)."""
    doc = json.loads(Path(json_path).read_text())
    return "\n".join(report([Score(**s) for s in doc["scores"]])[0])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.sigma_calibration", description=__doc__.split("\n\n")[0])
    ap.add_argument("specs", nargs="+", type=parse_spec, metavar="CELL=PROFILE:RECORDING[@FULL_AT]")
    ap.add_argument("--bias", type=float, action="append", default=None,
                    help="current-sensor offset (fraction of 1C) the estimator reads, as socd evaluate "
                    "--current-bias-c; repeat for each condition (default: 0 only)")
    ap.add_argument("--jobs", type=int, default=1, help="recordings run at once (default 1)")
    ap.add_argument("--json", type=Path, help="write every score and the choices here")
    args = ap.parse_args(argv)
    if len({s.cell for s in args.specs}) < 2:
        ap.error("leave-one-cell-out needs recordings of at least two cells")
    jobs = [(s, b) for s in args.specs for b in (args.bias or [0.0])]
    scores: list[Score] = []
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for k, result in enumerate(pool.map(score_recording, jobs), 1):
            scores += result
            print(f"  {k}/{len(jobs)} {result[0].cell} {result[0].recording} bias {result[0].bias_c:+g}C",
                  file=sys.stderr, flush=True)
    lines, choice = report(scores)
    print("\n".join(lines))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"scores": [asdict(s) for s in scores], **choice,
                                         "table": lines}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
