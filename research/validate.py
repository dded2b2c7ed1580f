"""Detection power of ``socd diagnose`` on recordings simulated with the estimator's own model.

The issue asks that the diagnosis be tested on recordings we simulate ourselves, at
subtle as well as clear levels, so that its thresholds are not tuned to the seven
labelled synthetic files.  This module simulates a 2 Ah cell (the model of
:mod:`service.cell.model` with one extension at a time) along random drive currents,
adds noise, runs the diagnosis exactly as ``socd diagnose --ocv ... --capacity-ah ...``
would (OCV table and capacity only), and tabulates the verdicts.

What it can and cannot say: the recordings come from the model diagnose fits, so there
is no model-form mismatch here (the PyBaMM files have 9-18 x noise of it); it measures
the detection limit of each effect above the noise and the false-positive rate on clean
recordings, not the accuracy on real cells.

    python -m research.validate [--seeds N] [--levels subtle,moderate,clear] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.cell.profile import (
    ArrheniusSpec,
    CellProfile,
    Extensions,
    HysteresisSpec,
    OcvCorrectionSpec,
    OcvSpec,
    ParameterPoint,
    SurfaceDiffusionSpec,
    kinetic_linear_ohm,
)
from service.cell.trajectory import simulate
from service.recording import save_recording

CAP = 2.0
DT = 4.0
N = 900  # one hour at 4 s
TRUE = ParameterPoint(r_ohm=0.030, r_ct=0.015, c_dl=600.0, m=0.9, r_df=0.020, c_df=9000.0, n=0.9)
V_NOISE = 0.001
I_NOISE = 0.002
LEVELS = ("subtle", "moderate", "clear")


def ocv_spec() -> OcvSpec:
    """An NMC-like OCV table (steep below 10 % SOC, a shallow dip at 55 %)."""
    soc = np.linspace(0, 1, 41)
    ocv = 3.3 + 0.75 * soc + 0.12 * np.tanh((soc - 0.08) / 0.05) - 0.06 * np.exp(-((soc - 0.55) / 0.1) ** 2)
    return OcvSpec(soc=soc.tolist(), ocv_v=[ocv.tolist()])


def base_profile() -> CellProfile:
    return CellProfile(capacity_ah=CAP, ocv=ocv_spec(), parameters=[TRUE])


def user_profile() -> CellProfile:
    """What diagnose is given: OCV + capacity; the parameters are a placeholder it refits."""
    return CellProfile(capacity_ah=CAP, ocv=ocv_spec(), parameters=[
        ParameterPoint(r_ohm=0.01, r_ct=0.01, c_dl=100.0, m=0.9, r_df=0.01, c_df=1000.0, n=0.8)])


def random_steps(rng: np.random.Generator, c_rates: tuple[float, ...], done: Callable[[list[float]], bool]) -> list[float]:
    """Current steps of 3-30 samples at C-rates drawn from ``c_rates``, with a rest of 20-80
    samples after 15 % of them, from a 15-sample opening rest until ``done(steps)``."""
    out: list[float] = [0.0] * 15
    while not done(out):
        out += [rng.choice(c_rates) * CAP] * int(rng.integers(3, 30))
        if rng.random() < 0.15:
            out += [0.0] * int(rng.integers(20, 80))
    return out


def current_profile(seed: int = 11) -> np.ndarray:
    """Random drive: steps of 0.5-2C discharge and 0.5-1C charge, with rests."""
    out = random_steps(np.random.default_rng(seed), (2.0, 1.5, 1.0, 1.0, 0.5, 0.0, -0.5, -1.0), lambda o: len(o) >= N)
    return np.array(out[:N], dtype=float)


def _ocv_bump(amplitude_v: float) -> OcvCorrectionSpec:
    """The cell's OCV differs from the table by a bump centred at 60 % SOC (OCV-curve error)."""
    soc = np.linspace(0, 1, 41)
    return OcvCorrectionSpec(soc=soc.tolist(), delta_v=(amplitude_v * np.exp(-((soc - 0.6) / 0.15) ** 2)).tolist())


def _arrhenius(scale: float) -> ArrheniusSpec:
    return ArrheniusSpec(ref_temp_c=25.0, ea_r_ohm_j_mol=25000.0 * scale, ea_r_ct_j_mol=45000.0 * scale,
                         ea_r_df_j_mol=45000.0 * scale)


#: effect -> level -> what is changed in the simulated cell (the "clear" level is the one
#: tests/test_diagnose.py requires diagnose to name)
def _slow_kinetics(i0_a: float) -> dict:
    """A cell with Butler–Volmer exchange current ``i0_a``.  The model's kinetic term is the drop
    *beyond* its linear part (:func:`service.cell.model.kinetic_overpotential`), which the
    resistances hold, so the linear part ``2RT/F / (2 i0)`` at 25 °C is added to ``R_ohm`` as a
    ``--kinetics`` fit keeps it; without it the cell's voltage would rise under a large discharge."""
    point = TRUE.model_copy(update={"r_ohm": TRUE.r_ohm + float(kinetic_linear_ohm(i0_a, 25.0))})
    return {"parameters": [point], "extensions": Extensions(kinetics_i0_a=i0_a)}


CASES: dict[str, dict[str, dict]] = {
    "none": {level: {} for level in LEVELS},
    "hysteresis": {lv: {"hysteresis": HysteresisSpec(u_h_max_v=u, rate=30.0), "u_h0": u}
                   for lv, u in zip(LEVELS, (0.005, 0.012, 0.025))},
    "capacity": {lv: {"extensions": Extensions(capacity_scale=s)} for lv, s in zip(LEVELS, (0.95, 0.90, 0.85))},
    # the sensor reads true + offset: the voltage follows the true current, whose rests are
    # exactly zero, and the recording holds the measured one
    "current_bias": {lv: {"bias_a": b} for lv, b in zip(LEVELS, (0.006, 0.014, 0.03))},
    # exchange currents below a healthy cell's (service.diagnosis.effects.KINETICS_MAX_I0_C = 0.1 C):
    # 0.09 / 0.06 / 0.03 C
    "kinetics": {lv: _slow_kinetics(f * CAP) for lv, f in zip(LEVELS, (0.09, 0.06, 0.03))},
    # slow solid diffusion: the surface SOC lags the bulk (gain of SOC per 1C, 10 min)
    "diffusion": {lv: {"extensions": Extensions(diffusion_surface=SurfaceDiffusionSpec(tau_s=600.0, gain=g))}
                  for lv, g in zip(LEVELS, (0.02, 0.04, 0.08))},
    "temperature": {lv: {"extensions": Extensions(arrhenius=_arrhenius(s)), "temp": "ramp"}
                    for lv, s in zip(LEVELS, (0.25, 0.5, 1.0))},
    "ocv": {lv: {"extensions": Extensions(ocv_correction=_ocv_bump(a))} for lv, a in zip(LEVELS, (0.005, 0.010, 0.020))},
}


def simulate_case(effect: str, level: str = "clear", seed: int = 0, case: dict | None = None) -> np.ndarray:
    """``[N, 4]`` columns time_s, current_a (measured), voltage_v, temperature_c.

    Seed 0 is the drive and noise of the test suite; other seeds change both.  ``case``
    replaces ``CASES[effect][level]`` (the same keys) to simulate a size outside the grid.
    """
    columns, _ = simulate_cell(CASES[effect][level] if case is None else case, current_profile(11 + seed), seed)
    return columns


def simulate_cell(case: dict, current_a: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The cell of ``case`` (a ``CASES`` entry) driven by the true ``current_a`` at ``DT``:
    ``([T, 4]`` columns time_s, current_a (measured: + sensor offset + noise), voltage_v
    (+ noise), temperature_c``, true SOC ``[T])``.  The SOC starts at 0.95."""
    case = dict(case)
    u_h0 = case.pop("u_h0", 0.0)
    temp_kind = case.pop("temp", "flat")
    bias_a = case.pop("bias_a", 0.0)
    prof = base_profile().model_copy(update=case)
    n = current_a.size
    t = np.arange(n) * DT
    rng = np.random.default_rng(5 + 1000 * seed)
    temp = np.linspace(5.0, 35.0, n) if temp_kind == "ramp" else 25.0 + 2.0 * np.sin(t / 900.0)
    v, soc = simulate(prof, t, current_a, temp, 0.95, u_h0=u_h0)
    v = v + rng.normal(0.0, V_NOISE, n)
    i_meas = current_a + bias_a + rng.normal(0.0, I_NOISE, n)
    return np.column_stack([t, i_meas, v, temp + rng.normal(0, 0.05, n)]), soc


def write_case(path: Path, effect: str, level: str = "clear", seed: int = 0, case: dict | None = None) -> Path:
    return save_recording(path, simulate_case(effect, level, seed, case), fmt="%.6f")


@dataclass
class Row:
    effect: str
    level: str
    seed: int
    verdict: str
    state: str
    top: str
    top_score: float
    seconds: float

    @property
    def right(self) -> bool:
        return self.verdict == self.effect


def run_grid(effects: list[str], levels: list[str], seeds: int, workdir: Path, progress=None) -> list[Row]:
    from service.diagnosis.pipeline import DiagnoseOptions, run_diagnosis
    from service.recording import load_recording

    say = progress or (lambda _m: None)
    rows = []
    jobs = [(e, lv, s) for e in effects if e != "none" for lv in levels for s in range(seeds)]
    if "none" in effects:  # clean recordings: as many drives as one effect gets (levels x seeds)
        jobs += [("none", "-", s) for s in range(len(levels) * seeds)]
    for k, (effect, level, seed) in enumerate(jobs, 1):
        path = write_case(workdir / f"{effect}_{level}_{seed}.csv", effect, "clear" if effect == "none" else level, seed)
        t0 = time.perf_counter()
        dg = run_diagnosis(load_recording(path), user_profile(), DiagnoseOptions())
        row = Row(effect, level, seed, dg.verdict, dg.assessment["state"], dg.effects[0].name,
                  float(dg.effects[0].score), time.perf_counter() - t0)
        rows.append(row)
        say(f"[{k}/{len(jobs)}] {effect:12s} {level:8s} seed {seed}: {row.verdict}"
            f" ({'right' if row.right else 'wrong'}, {row.seconds:.0f} s)")
    return rows


def table(rows: list[Row], levels: list[str]) -> str:
    """Markdown: per effect and level, right/total and the wrong verdicts."""
    effects = list(dict.fromkeys(r.effect for r in rows))
    out = ["| effect | " + " | ".join(levels) + " |", "|---|" + "---|" * len(levels)]
    def cell(rs: list[Row]) -> str:
        wrong = sorted({r.verdict for r in rs if not r.right})
        return f"{sum(r.right for r in rs)}/{len(rs)}" + (f" (else: {', '.join(wrong)})" if wrong else "")

    for e in effects:
        if e == "none":  # clean drives have no level: one cell over all of them
            cells = [cell([r for r in rows if r.effect == e])] + [""] * (len(levels) - 1)
        else:
            cells = [cell([r for r in rows if r.effect == e and r.level == lv]) for lv in levels]
        out.append(f"| {e} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.validate", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=2, help="drives/noise draws per effect and level (default 2)")
    ap.add_argument("--levels", default=",".join(LEVELS), help="comma-separated subset of subtle,moderate,clear")
    ap.add_argument("--effects", default=",".join(CASES), help="comma-separated subset of " + ",".join(CASES))
    ap.add_argument("--workdir", default="out/validate", help="where the simulated CSVs are written")
    ap.add_argument("--json", help="write the rows as JSON")
    args = ap.parse_args(argv)
    levels = [lv.strip() for lv in args.levels.split(",") if lv.strip()]
    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    bad = [lv for lv in levels if lv not in LEVELS] + [e for e in effects if e not in CASES]
    if bad or args.seeds < 1:
        print(f"validate: unknown level/effect {bad} or --seeds < 1", file=sys.stderr)
        return 2
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    rows = run_grid(effects, levels, args.seeds, work, progress=lambda m: print(m, file=sys.stderr, flush=True))
    print(table(rows, levels))
    named = [r for r in rows if r.effect != "none"]
    clean = [r for r in rows if r.effect == "none"]
    print(f"\nnamed right: {sum(r.right for r in named)}/{len(named)}; clean named as an effect: "
          f"{sum(not r.right for r in clean)}/{len(clean)}; mean run {np.mean([r.seconds for r in rows]):.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps([r.__dict__ for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
