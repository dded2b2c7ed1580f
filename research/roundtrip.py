"""From a diagnosis to the online estimator: does the extended profile help SOC estimation?

``socd diagnose --save-profile`` writes the base model plus the extension it named; the
issue asks that this profile be used by ``socd evaluate`` and by the service online.
This module closes that loop on recordings simulated with our own model (as
:mod:`research.validate`), one effect at a time:

1. diagnose a one-hour drive of a cell with the effect, from the OCV table and the
   capacity only (the simulated recording of the validation grid, seed 0);
2. keep the base profile diagnose fitted, and the profile extended by the candidate of
   the simulated effect (whether or not it was significant: the verdict is reported
   beside it);
3. score both profiles with the loop of ``socd evaluate``
   (:func:`service.evaluation.run.evaluate_recordings`, in-process) on a *second* recording
   of the same cell that diagnose never saw: a deeper discharge, 0.95 → about 0.15 SOC,
   with its true SOC as ``soc_true``; the estimators start 0.20 wrong as in every evaluation.

    python -m research.roundtrip [--effects diffusion,temperature] [--level clear] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from research.validate import (
    CASES,
    DT,
    LEVELS,
    random_steps,
    simulate_cell,
    user_profile,
    write_case,
)
from service.cell.units import SECONDS_PER_HOUR
from service.evaluation.run import EstimatorScore, evaluate_recordings

#: the estimators scored (the service's default pipeline and the paper's)
ESTIMATORS = ("foukf", "fomiukf")
#: charge the scoring drive takes out of the cell, Ah (0.95 → 0.15 SOC of the 2 Ah cell)
SCORE_DISCHARGE_AH = 1.6


def score_drive(seed: int) -> np.ndarray:
    """True current of the scoring recording at ``validate.DT``: steps of 0.5-2C discharge,
    0.5C charge and rests until ``SCORE_DISCHARGE_AH`` is out, then a 10 min rest."""
    out = random_steps(np.random.default_rng(100 + seed), (2.0, 1.5, 1.0, 1.0, 0.5, 0.0, -0.5),
                       lambda o: np.sum(o) * DT / SECONDS_PER_HOUR >= SCORE_DISCHARGE_AH)
    return np.array(out + [0.0] * int(600 / DT), dtype=float)


@dataclass
class RoundTrip:
    effect: str
    level: str
    verdict: str
    candidate_score: float
    candidate_significant: bool
    #: estimator -> SOC RMSE after 600 s [%] / voltage RMSE [mV], with the base and the extended profile
    soc_rmse_base_pct: dict[str, float]
    soc_rmse_extended_pct: dict[str, float]
    v_rmse_base_mv: dict[str, float]
    v_rmse_extended_mv: dict[str, float]


def _evaluate(cell: Path, recording: Path) -> dict[str, EstimatorScore]:
    """Score :data:`ESTIMATORS` with the profile ``cell`` as ``socd evaluate`` does by default
    (the recording's start, SOC 0.20 wrong, default settings): its loop, called in-process."""
    from service.cell.profile import load_profile
    from service.estimators.registry import create
    from service.estimators.settings import EstimatorSettings
    from service.recording import load_recording

    estimators = [create(name, EstimatorSettings()) for name in ESTIMATORS]
    (run,) = evaluate_recordings([load_recording(recording)], load_profile(cell), estimators)
    return {r.estimator: r for r in run.scores}


def run_effect(effect: str, level: str, workdir: Path, progress=None) -> RoundTrip:
    """Diagnose, save both profiles, score both on the unseen recording (module docstring)."""
    from service.cell.profile import save_profile
    from service.diagnosis.pipeline import DiagnoseOptions, run_diagnosis
    from service.recording import load_recording

    say = progress or (lambda _m: None)
    diag_csv = write_case(workdir / f"{effect}_{level}_diagnose.csv", effect, level, 0)
    say(f"{effect}: diagnosing {diag_csv.name} ...")
    dg = run_diagnosis(load_recording(diag_csv), user_profile(), DiagnoseOptions())
    candidate = dg.outcome(effect)
    base_path = workdir / f"{effect}_{level}_base.toml"
    ext_path = workdir / f"{effect}_{level}_extended.toml"
    save_profile(dg.base_profile, base_path)
    save_profile(candidate.profile, ext_path)

    columns, soc = simulate_cell(CASES[effect][level], score_drive(1), 1)
    score_csv = workdir / f"{effect}_{level}_score.csv"
    np.savetxt(score_csv, np.column_stack([columns, soc]), delimiter=",", comments="", fmt="%.6f",
               header="time_s,current_a,voltage_v,temperature_c,soc_true")
    say(f"{effect}: verdict {dg.verdict}; scoring both profiles on {score_csv.name} ...")
    base = _evaluate(base_path, score_csv)
    ext = _evaluate(ext_path, score_csv)
    return RoundTrip(
        effect=effect, level=level, verdict=dg.verdict,
        candidate_score=float(candidate.score), candidate_significant=bool(candidate.significant),
        soc_rmse_base_pct={k: base[k].soc_rmse_after_600s_pct for k in ESTIMATORS},
        soc_rmse_extended_pct={k: ext[k].soc_rmse_after_600s_pct for k in ESTIMATORS},
        v_rmse_base_mv={k: base[k].v_rmse_mv for k in ESTIMATORS},
        v_rmse_extended_mv={k: ext[k].v_rmse_mv for k in ESTIMATORS},
    )


def table(rows: list[RoundTrip]) -> str:
    """Markdown: per effect, the verdict and each estimator's SOC / voltage RMSE base → extended."""
    head = ["effect", "verdict (candidate held-out gain)"]
    for name in ESTIMATORS:
        head += [f"{name} SOC RMSE >600 s, base → extended [%]", f"{name} V RMSE [mV]"]
    out = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in rows:
        cells = [r.effect, f"{r.verdict} ({100 * r.candidate_score:+.1f} %)"]
        for name in ESTIMATORS:
            cells += [f"{r.soc_rmse_base_pct[name]:.2f} → {r.soc_rmse_extended_pct[name]:.2f}",
                      f"{r.v_rmse_base_mv[name]:.1f} → {r.v_rmse_extended_mv[name]:.1f}"]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    effects_all = [e for e in CASES if e != "none"]
    ap = argparse.ArgumentParser(prog="python -m research.roundtrip", description=__doc__.split("\n\n")[0])
    ap.add_argument("--effects", default=",".join(effects_all), help="comma-separated subset of " + ",".join(effects_all))
    ap.add_argument("--level", default="clear", choices=LEVELS, help="size of the simulated effect (default clear)")
    ap.add_argument("--workdir", default="out/roundtrip", help="where the recordings and profiles go")
    ap.add_argument("--json", help="write the rows as JSON")
    args = ap.parse_args(argv)
    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    bad = [e for e in effects if e not in effects_all]
    if bad or not effects:
        print(f"roundtrip: unknown effect(s) {bad}; choose from {','.join(effects_all)}", file=sys.stderr)
        return 2
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    rows = [run_effect(e, args.level, work, progress=lambda m: print(m, file=sys.stderr, flush=True)) for e in effects]
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(r) for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
