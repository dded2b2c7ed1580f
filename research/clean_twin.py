"""The model-form floor of a labelled synthetic recording, from its clean twin.

Each labelled recording in ``../shared/data/synthetic`` was simulated with PyBaMM; its
``labels.json`` entry names the model (``SPMe`` or ``DFN``, lumped thermal), the parameter set,
the initial SOC and the current-sensor offset.  The same simulation with the effect left out
(the same true current, the same start, the default 25 °C ambient) is the recording's *clean
twin*: the voltage the cell would have shown without the effect.  Its difference from the
recording is checked against the label's ``voltage_diff_vs_no_effect_mv``, so a twin that is not
the generator's no-effect run is reported, not used silently.

Diagnosed exactly as ``socd diagnose --ocv ... --capacity-ah ...`` diagnoses the recording, the
twin's base held-out RMSE is the **floor**: what the equivalent circuit leaves on this cell and
drive with no effect at all.  An extension can at best take the recording's held-out RMSE down
to about the floor, so

    excess removed = (before - after) / (before - floor)

is the share of the *effect's* part of the held-out RMSE that the named extension removed,
beside the plain cut ``(before - after) / before`` the issue aims at (>= 50 %).  The twins are
also clean recordings of the exact generator on the same drives: their verdicts must be
``none``.

Uses the labels (truth) only to build the twins and to read the result; the diagnosis of the
recording never sees them.  Needs PyBaMM (``pip install -e .[research]``).

    python -m research.clean_twin [--data ../shared/data/synthetic] [--stems a,b]
        [--jobs 2] [--workdir out/clean_twin] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

DEFAULT_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "synthetic"
#: a twin whose difference from the recording departs from the label's by more than this
#: (after the voltage noise is taken out) is not the generator's no-effect run
FIDELITY_TOL_MV = 1.0
FIDELITY_TOL_REL = 0.05


class TwinError(ValueError):
    """A labelled recording whose twin cannot be built (names the stem and the reason)."""


@dataclass
class TwinRow:
    stem: str
    effect: str  # the label
    model: str
    twin_diff_mv: float  # RMS of recording - twin, voltage noise taken out
    label_diff_mv: float  # the label's voltage_diff_vs_no_effect_mv.rms_mv
    twin_faithful: bool
    twin_verdict: str
    twin_state: str
    verdict: str
    split: str  # held-out protocol of the labelled effect's outcome
    floor_mv: float  # the twin's base held-out RMSE on that split
    before_mv: float  # the labelled effect's outcome on the recording
    after_mv: float
    seconds: float

    @property
    def cut(self) -> float:
        return (self.before_mv - self.after_mv) / self.before_mv

    @property
    def best_cut(self) -> float:
        """The cut an extension would make by taking the recording down to its twin's floor."""
        return max(self.before_mv - self.floor_mv, 0.0) / self.before_mv

    @property
    def excess_removed(self) -> float | None:
        return excess_removed(self.before_mv, self.after_mv, self.floor_mv)

    def to_json(self) -> dict:
        return asdict(self) | {"cut": round(self.cut, 4), "best_cut": round(self.best_cut, 4),
                               "excess_removed": None if self.excess_removed is None else round(self.excess_removed, 4)}

    @classmethod
    def from_json(cls, d: dict) -> TwinRow:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__})


def excess_removed(before_mv: float, after_mv: float, floor_mv: float) -> float | None:
    """``(before - after) / (before - floor)``; ``None`` when the recording's base is not above
    its twin's floor (the effect left nothing for an extension to remove)."""
    if not before_mv > floor_mv:
        return None
    return (before_mv - after_mv) / (before_mv - floor_mv)


def noise_free_rms_mv(diff_v: np.ndarray, v_sigma_mv: float) -> float:
    """RMS of a recording-minus-twin difference in mV with the voltage noise taken out."""
    rms = 1e3 * float(np.sqrt(np.mean(np.square(diff_v))))
    return math.sqrt(max(rms**2 - v_sigma_mv**2, 0.0))


def faithful(twin_mv: float, label_mv: float) -> bool:
    return abs(twin_mv - label_mv) <= FIDELITY_TOL_MV + FIDELITY_TOL_REL * label_mv


def load_label(data: Path, stem: str) -> dict:
    path = data / "labels.json"
    try:
        labels = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise TwinError(f"{path}: no labels file") from exc
    if stem not in labels:
        raise TwinError(f"{path}: no label for '{stem}'")
    label = labels[stem]
    missing = [k for k in ("model", "cell", "soc0", "current_offset_a", "noise", "voltage_diff_vs_no_effect_mv")
               if k not in label]
    if missing:
        raise TwinError(f"{path}: label '{stem}' lacks {', '.join(missing)}")
    return label


def twin_current(current_a: np.ndarray, label: dict) -> np.ndarray:
    """The current the cell carried: the recorded one less the sensor's offset (the label's
    ``current_offset_a``; the recorded current is true + offset + noise)."""
    return current_a - float(label["current_offset_a"])


def simulate_twin(time_s: np.ndarray, current_a: np.ndarray, label: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(voltage_v, temperature_c)`` of the clean twin along ``current_a`` (the true current)."""
    from research.validate_pybamm import _pybamm

    pybamm = _pybamm()
    sets = {name.lower(): name for name in pybamm.parameter_sets}
    if label["cell"].lower() not in sets:
        raise TwinError(f"parameter set '{label['cell']}' is not one of PyBaMM's")
    models = {"spme": pybamm.lithium_ion.SPMe, "dfn": pybamm.lithium_ion.DFN, "spm": pybamm.lithium_ion.SPM}
    if label["model"].lower() not in models:
        raise TwinError(f"model '{label['model']}' is not one of {', '.join(models)}")
    pv = pybamm.ParameterValues(sets[label["cell"].lower()]).set_initial_state(float(label["soc0"]))
    pv["Current function [A]"] = pybamm.Interpolant(time_s, current_a, pybamm.t, interpolator="linear")
    model = models[label["model"].lower()]({"thermal": "lumped"})
    # regen near full may pass the upper cut-off for a moment; the recording goes on there
    model.events = [e for e in model.events if "Maximum voltage" not in e.name]
    rtol, atol = label.get("solver_rtol_atol", (1e-5, 1e-7))
    sim = pybamm.Simulation(model, parameter_values=pv, solver=pybamm.IDAKLUSolver(rtol=rtol, atol=atol))
    sol = sim.solve(t_eval=[float(time_s[0]), float(time_s[-1])], t_interp=time_s)
    return sol["Voltage [V]"].entries, sol["X-averaged cell temperature [C]"].entries


def run_stem(job: tuple[str, str, str]) -> TwinRow:
    """Build, check, write and diagnose one recording's twin, and diagnose the recording."""
    from service.cell.ocv import load_ocv_csv
    from service.diagnosis.pipeline import DiagnoseOptions, run_diagnosis, table_profile
    from service.recording import load_recording, save_recording

    data_dir, stem, workdir = Path(job[0]), job[1], Path(job[2])
    t0 = time.perf_counter()
    label = load_label(data_dir, stem)
    meta = json.loads((data_dir / f"{stem}.meta.json").read_text())
    rec = load_recording(data_dir / f"{stem}.csv")
    soc, ocv = load_ocv_csv(data_dir / f"{stem}_ocv.csv")
    profile = table_profile(stem, float(meta["capacity_ah"]), soc, ocv)

    i_true = twin_current(rec.current_a, label)
    v_twin, t_twin = simulate_twin(rec.time_s, i_true, label)
    n = v_twin.size
    if n < len(rec):
        raise TwinError(f"{stem}: the twin stopped at {n} of {len(rec)} samples")
    noise = label["noise"]
    twin_mv = noise_free_rms_mv(rec.voltage_v - v_twin, float(noise["v_sigma_mv"]))
    label_mv = float(label["voltage_diff_vs_no_effect_mv"]["rms_mv"])
    # the twin as a recording: the sensor reads the true current with the recording's own
    # current noise, the voltage and temperature get the labelled noise
    rng = np.random.default_rng(zlib.crc32(stem.encode()))
    workdir.mkdir(parents=True, exist_ok=True)
    twin_csv = workdir / f"{stem}_twin.csv"
    save_recording(twin_csv, np.column_stack([
        rec.time_s, np.round(i_true, 4),
        np.round(v_twin + rng.normal(0.0, 1e-3 * float(noise["v_sigma_mv"]), n), 4),
        np.round(t_twin + rng.normal(0.0, float(noise.get("t_sigma_c", 0.1)), n), 2),
    ]))

    twin = load_recording(twin_csv)  # read back: the twin is diagnosed from the file a user would have
    dg = run_diagnosis(rec, profile, DiagnoseOptions())
    dg_twin = run_diagnosis(twin, profile, DiagnoseOptions())
    for name, d in (("recording", dg), ("twin", dg_twin)):
        (workdir / f"{stem}_{name}.diagnosis.json").write_text(json.dumps(d.to_json(), indent=1, default=float))
    effect = label.get("effect", "none")
    names = [e.name for e in dg.effects]
    outcome = dg.outcome(effect) if effect in names else dg.effects[0]
    floor = float(dg_twin.base["rmse_heldout_mv"])
    if outcome.split != "chronological":
        # the floor on the split the effect was scored on: the twin's base alone there
        floor = float(run_diagnosis(twin, profile,
                                    DiagnoseOptions(split=outcome.split, effects=())).base["rmse_heldout_mv"])
    return TwinRow(stem=stem, effect=effect, model=label["model"], twin_diff_mv=round(twin_mv, 2),
                   label_diff_mv=label_mv, twin_faithful=faithful(twin_mv, label_mv),
                   twin_verdict=dg_twin.verdict, twin_state=dg_twin.assessment.get("state", ""), verdict=dg.verdict,
                   split=outcome.split, floor_mv=round(floor, 3), before_mv=round(outcome.rmse_before_mv, 3),
                   after_mv=round(outcome.rmse_after_mv, 3), seconds=round(time.perf_counter() - t0, 1))


def table(rows: list[TwinRow]) -> str:
    head = ("| recording | label | twin − recording (label) mV | twin verdict | verdict | split | floor mV "
            "| before → after mV | cut | best cut (to the floor) | excess removed |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        ex = "–" if r.excess_removed is None else f"{100 * r.excess_removed:.0f} %"
        mark = "" if r.twin_faithful else " ✗"
        lines.append(f"| {r.stem} | {r.effect} | {r.twin_diff_mv:.2f} ({r.label_diff_mv:.2f}){mark} | {r.twin_verdict} "
                     f"| {r.verdict} | {r.split} | {r.floor_mv:.2f} | {r.before_mv:.2f} → {r.after_mv:.2f} "
                     f"| {100 * r.cut:+.1f} % | {100 * r.best_cut:.1f} % | {ex} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.clean_twin", description=__doc__.split("\n\n")[0],
                                 epilog="Each row: the twin's check against the label, the twin's own verdict "
                                        "(must be none), and the floor beside the recording's before/after.")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder with labels.json and the recordings "
                    "(default: %(default)s)")
    ap.add_argument("--stems", help="comma-separated stems (default: every stem in labels.json)")
    ap.add_argument("--jobs", type=int, default=1, help="recordings at once (default 1)")
    ap.add_argument("--workdir", default="out/clean_twin", help="where the twins and the diagnoses are written")
    ap.add_argument("--json", help="write the rows as JSON")
    ap.add_argument("--show", metavar="JSON", help="print the table of an earlier run's --json and stop")
    args = ap.parse_args(argv)
    if args.show:
        try:
            rows = [TwinRow.from_json(d) for d in json.loads(Path(args.show).read_text())]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            ap.error(f"--show {args.show}: not a clean_twin --json file ({exc})")
        print(table(rows))
        return 0
    labels_path = args.data / "labels.json"
    if not labels_path.is_file():
        ap.error(f"{labels_path}: no labels file (give --data)")
    labels = json.loads(labels_path.read_text())
    stems = [s for s in args.stems.split(",") if s] if args.stems else list(labels)
    unknown = [s for s in stems if s not in labels]
    if unknown:
        ap.error(f"--stems: no label for {', '.join(unknown)} in {labels_path}")
    jobs = [(str(args.data), s, args.workdir) for s in stems]
    rows: list[TwinRow] = []
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for k, row in enumerate(pool.map(run_stem, jobs), 1):
            rows.append(row)
            print(f"[{k}/{len(jobs)}] {row.stem}: twin {row.twin_verdict}, floor {row.floor_mv:.2f} mV "
                  f"({row.seconds:.0f} s)", file=sys.stderr, flush=True)
    print(table(rows))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps([r.to_json() for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
