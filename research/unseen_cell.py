"""The held-out check of issue 25 rehearsed on PyBaMM cells nobody tuned on.

The issue re-measures ``socd`` on a cell the team never saw, in one shape: a C/20 OCV test and
one US06 per temperature go into ``socd fit`` with no other flag, and the cell's other drive
cycles are scored with ``socd evaluate --estimator fomiukf --estimator ecm2rc-ekf``.  The shared
real cells are the ones every default was chosen on; this module builds cells that were not:

* ``build`` simulates each PyBaMM parameter set (SPMe with a lumped thermal model, the cell
  heats under load) at the ambient temperatures asked for: a C/20 discharge and C/20 charge
  (the OCV test, logged every 60 s like the Panasonic one) and the current of every shared
  Panasonic 18650PF drive cycle at 25 °C, scaled to the cell's capacity (the same C-rates),
  from full charge to the lower cut-off.  Noise as :mod:`research.validate_pybamm` (voltage
  σ 1.5 mV, current 0.5 % + 5 mA, temperature 0.1 K).  PyBaMM's models have no OCV hysteresis;
  ``--hysteresis-mv`` adds a one-state one (Zeng Eq. 1, as :mod:`research.validate_pybamm` does).
  Every recording carries ``soc_true``: the coulomb count from full over the OCV test's C/20
  discharge capacity, which is also the capacity the user is told.
* ``run`` is the issue's two commands per cell, unchanged: ``socd fit`` on every ambient's OCV test
  and US06 (``<cell>.toml``), then ``socd evaluate --estimator fomiukf --estimator ecm2rc-ekf`` on
  every other drive (``<cell>_eval.json``; SOC RMSE after 600 s from a ±20 % start, as the issue
  scores).  ``--settings`` and ``--current-bias-c`` score the same profile another way, for a
  leave-one-cell-out table beside the shared cells (``research.nested_tuning --by cell``).

Needs PyBaMM (``pip install -e .[research]``).  CI builds one cell in its test
(``tests/test_unseen_cell.py``); the tables in ``docs/results/`` are not run there.

    python -m research.unseen_cell build [--cells Chen2020,...] [--ambients 25,10,0] [--jobs 2]
    python -m research.unseen_cell run [--cells ...] [--ambients ...] [--settings S.toml] [--tag T]
        [--fit-flags=FLAGS --profile-tag T]
    python -m research.unseen_cell fit [...]   # the profile alone, as ``run`` fits it
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from research.validate_pybamm import _pybamm, hysteresis_state, parameter_values, sensor_readings
from service.cell.coulomb import coulomb_soc
from service.recording import load_recording, save_recording

#: NMC and NCA-like sets with a lumped thermal model that simulate the drives from full charge
CELLS = ("Chen2020", "Mohtat2020", "Marquis2019")
DEFAULT_WORKDIR = Path("out/unseen_cell")
PANASONIC = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "panasonic_18650pf"
PANASONIC_AH = 2.9
#: the Panasonic 25 °C drive cycles whose current shapes the cells are driven with; US06 is the fit's
DRIVES = ("US06", "HWFETa", "HWFETb", "LA92", "NN", "Cycle1", "Cycle2", "Cycle3", "Cycle4")
FIT_DRIVE = "US06"
#: the Panasonic 25 °C pulse test (discharge pulses and rests every 10 % SOC), built beside the drives:
#: what a user characterises from without an OCV test (``--fit-drive HPPC``)
PULSE_DRIVE = "HPPC"
#: the recordings built beside the drives (the pulse test)
PULSE_DRIVES = (PULSE_DRIVE,)
OCV_TEST_C = 20.0
OCV_TEST_LOG_S = 60.0
#: W/m²/K: a cell in a ventilated chamber.  PyBaMM's sets ship 5-10, which heats Chen2020's
#: 5 Ah cell 19 K over the US06 drive; at 30 it warms 8.5 K, as the Panasonic cell does (7 K)
HEAT_TRANSFER = 30.0


@dataclass(frozen=True)
class Job:
    """One recording to simulate: ``drive`` is a name of :data:`DRIVES` or ``"ocv"``."""

    cell: str
    ambient_c: float
    drive: str
    seed: int
    hysteresis_v: float = 0.0  # half-gap of the OCV hysteresis added to PyBaMM's voltage

    @property
    def stem(self) -> str:
        return f"{self.cell}_{_temp_tag(self.ambient_c)}_{self.drive}"


def _temp_tag(t: float) -> str:
    return f"{'m' if t < 0 else ''}{abs(t):g}C"


def _at_ambient(cell: str, ambient_c: float):
    pv = parameter_values(cell)
    kelvin = 273.15 + ambient_c
    pv.update({"Ambient temperature [K]": kelvin, "Initial temperature [K]": kelvin,
               "Total heat transfer coefficient [W.m-2.K-1]": HEAT_TRANSFER})
    return pv


def _noisy(rng: np.random.Generator, time_s, current_a, voltage_v, temp_c) -> np.ndarray:
    """The recording's four columns, read through :func:`research.validate_pybamm.sensor_readings`."""
    i, v, t = sensor_readings(rng, current_a, voltage_v, temp_c)
    return np.column_stack([time_s, np.round(i, 5), np.round(v, 5), np.round(t, 2)])


def _hysteresis(job: Job, time_s: np.ndarray, current_a: np.ndarray, capacity_ah: float) -> np.ndarray | float:
    """The OCV hysteresis PyBaMM's models lack, ``job.hysteresis_v`` × Zeng Eq. 1's state; every
    recording starts full, on the after-charge branch."""
    if not job.hysteresis_v:
        return 0.0
    return job.hysteresis_v * hysteresis_state(time_s, current_a, capacity_ah, start=1.0)


def c20_solution(cell: str, ambient_c: float, charge: bool = True):
    """PyBaMM's solution of the OCV test at ``ambient_c`` from full: an hour's rest, a C/20
    discharge to the lower cut-off and (``charge``) an hour's rest, a C/20 charge to the upper one
    and an hour's rest, logged every 60 s."""
    pybamm = _pybamm()
    pv = _at_ambient(cell, ambient_c)
    steps = ["Rest for 1 hour", f"Discharge at C/{OCV_TEST_C:g} until {pv['Lower voltage cut-off [V]']} V"]
    if charge:
        steps += ["Rest for 1 hour", f"Charge at C/{OCV_TEST_C:g} until {pv['Upper voltage cut-off [V]']} V",
                  "Rest for 1 hour"]
    exp = pybamm.Experiment(steps, period=f"{OCV_TEST_LOG_S:g} seconds")
    sim = pybamm.Simulation(pybamm.lithium_ion.SPMe({"thermal": "lumped"}), parameter_values=pv, experiment=exp)
    return sim.solve(initial_soc=1.0)


#: V below the lower cut-off an OCV test's solution may reach (a solver's last step past the stop)
CUT_OFF_OVERSHOOT_V = 0.05


def ocv_test(job: Job) -> tuple[np.ndarray, float]:
    """:func:`c20_solution` read as a recording with its sensors' noise (and ``job``'s hysteresis);
    returns the recording and its discharge capacity (Ah)."""
    sol = c20_solution(job.cell, job.ambient_c)
    t = sol["Time [s]"].entries
    low, lowest = float(parameter_values(job.cell)["Lower voltage cut-off [V]"]), float(np.min(sol["Voltage [V]"].entries))
    if lowest < low - CUT_OFF_OVERSHOOT_V:  # the experiment's stop at the cut-off was stepped over
        raise RuntimeError(f"{job.stem}: PyBaMM's C/{OCV_TEST_C:g} discharge ran on to {lowest:.2f} V, past the "
                           f"{low:g} V lower cut-off: its solution is not a cell's OCV test")
    keep = np.concatenate([[True], np.diff(t) > 1e-6])
    capacity = float(np.max(sol["Discharge capacity [A.h]"].entries))
    current = sol["Current [A]"].entries[keep]
    voltage = sol["Voltage [V]"].entries[keep] + _hysteresis(job, t[keep], current, capacity)
    data = _noisy(np.random.default_rng(job.seed), t[keep], current, voltage,
                  sol["X-averaged cell temperature [C]"].entries[keep])
    return data, capacity


def drive(job: Job, capacity_ah: float) -> np.ndarray:
    """The Panasonic 25 °C ``job.drive`` current at the same C-rate, from full to the lower cut-off;
    columns time_s, current_a, voltage_v, temperature_c, soc_true."""
    pybamm = _pybamm()
    rec = load_recording(PANASONIC / f"pan18650pf_25C_{job.drive}.csv")
    t = np.round(rec.time_s - rec.time_s[0], 3)
    current = rec.current_a * capacity_ah / PANASONIC_AH
    pv = _at_ambient(job.cell, job.ambient_c).set_initial_state(1.0)
    pv["Current function [A]"] = _current_function(pybamm, job, t, current)
    model = pybamm.lithium_ion.SPMe({"thermal": "lumped"})
    # regen near full may pass the upper cut-off for a moment: only the lower one ends a drive
    model.events = [e for e in model.events if "Maximum voltage" not in e.name]
    sim = pybamm.Simulation(model, parameter_values=pv, solver=pybamm.IDAKLUSolver())
    sol = sim.solve(t_eval=_solver_stops(job, t, current, capacity_ah), t_interp=t)
    n = sol["Time [s]"].entries.size
    q = sol["Discharge capacity [A.h]"].entries
    voltage = sol["Voltage [V]"].entries + _hysteresis(job, t[:n], current[:n], capacity_ah)
    data = _noisy(np.random.default_rng(job.seed), t[:n], current[:n], voltage,
                  sol["X-averaged cell temperature [C]"].entries)
    soc = np.round(1.0 - q / capacity_ah, 6)
    if job.drive in PULSE_DRIVES:  # the recording must hold the charge the cell gave
        counted = (1.0 - float(coulomb_soc(t[:n], current[:n], capacity_ah, 1.0)[-1])) * capacity_ah
        if abs(float(q[-1]) - counted) > 0.01 * capacity_ah:
            raise RuntimeError(f"{job.stem}: the solver drew {float(q[-1]):.3f} Ah, the recording counts {counted:.3f} Ah")
    return np.column_stack([data, soc])


def _current_function(pybamm, job: Job, t: np.ndarray, current: np.ndarray):
    """The current PyBaMM draws.  A drive cycle's 1 s samples, linearly interpolated.  A pulse test's
    as the estimators count it, each sample held over the interval before it (backward zero-order
    hold): its log is sparse in the rests, and a line from a pulse's last sample to the next one a
    minute later would draw charge the recording does not hold."""
    if job.drive not in PULSE_DRIVES:
        return pybamm.Interpolant(t, current, pybamm.t, interpolator="linear")
    eps = 1e-3
    t_step = np.concatenate([[t[0]], np.column_stack([t[:-1] + eps, t[1:]]).ravel()])
    i_step = np.concatenate([[current[0]], np.repeat(current[1:], 2)])
    return pybamm.Interpolant(t_step, i_step, pybamm.t, interpolator="linear")


def _solver_stops(job: Job, t: np.ndarray, current: np.ndarray, capacity_ah: float) -> np.ndarray:
    """Where the solver must stop: a pulse test's every current step (over its long rests the solver's
    steps grow to hours and would pass a pulse unseen); a drive cycle's current changes every second,
    which keeps the steps short, so only its ends."""
    if job.drive not in PULSE_DRIVES:
        return np.array([0.0, float(t[-1])])
    step_at = np.flatnonzero(np.abs(np.diff(current)) > 0.01 * capacity_ah)
    return np.unique(np.concatenate([[0.0, float(t[-1])], t[step_at], t[step_at + 1]]))


def build_cell(cell: str, ambient_c: float, workdir: Path, seed: int, hysteresis_v: float = 0.0) -> str:
    """Every recording of one cell at one ambient (skips what is already on disk)."""
    workdir.mkdir(parents=True, exist_ok=True)
    ocv_job = Job(cell, ambient_c, "ocv", seed, hysteresis_v)
    meta_path = workdir / f"{ocv_job.stem}.json"
    if meta_path.exists():
        capacity = json.loads(meta_path.read_text())["capacity_ah"]
    else:
        data, capacity = ocv_test(ocv_job)
        save_recording(workdir / f"{ocv_job.stem}.csv", data, fmt="%.5f")
        meta_path.write_text(json.dumps({"cell": cell, "ambient_c": ambient_c, "capacity_ah": capacity,
                                         "hysteresis_v": hysteresis_v}))
    for k, name in enumerate((*DRIVES, *PULSE_DRIVES)):
        job = Job(cell, ambient_c, name, seed + 1 + k, hysteresis_v)
        out = workdir / f"{job.stem}.csv"
        if not out.exists():
            save_recording(out, drive(job, capacity), fmt="%.5f")
    return f"{cell} {_temp_tag(ambient_c)}: {capacity:.4f} Ah, {len(DRIVES)} drives, {len(PULSE_DRIVES)} pulse test(s)"


#: how a line of ``build``'s output starts when a cell-ambient could not be built
NOT_BUILT = "not built: "


def _build_one(args: tuple[str, float, str, int, float]) -> str:
    """:func:`build_cell`'s line, or :data:`NOT_BUILT` and why where PyBaMM's solution is not a
    cell's (the other cell-ambients still build)."""
    cell, ambient, workdir, seed, hysteresis_v = args
    try:
        return build_cell(cell, ambient, Path(workdir), seed, hysteresis_v)
    except RuntimeError as exc:
        return f"{NOT_BUILT}{exc}"


@dataclass(frozen=True)
class RunOptions:
    """How :func:`run_cell` fits and scores: extra ``socd fit`` flags (they name the profile by
    ``profile_tag``; a profile on disk is reused unless ``refit``), and ``socd evaluate`` options."""

    fit_flags: tuple[str, ...] = ()
    profile_tag: str = ""
    refit: bool = False
    estimators: tuple[str, ...] = ("fomiukf", "ecm2rc-ekf")
    settings: Path | None = None
    current_bias_c: float = 0.0
    tag: str = ""
    #: the ambients whose OCV test joins the fit (None: every ambient's; empty: none)
    ocv_ambients: tuple[float, ...] | None = None
    #: the recording fitted at every ambient: US06, or the pulse test (then every drive is scored)
    fit_drive: str = FIT_DRIVE


def told_capacity_ah(cell: str, ambients: Sequence[float], workdir: Path) -> float:
    """The capacity ``socd fit`` is told: the C/20 discharge of the OCV test at the warmest of
    ``ambients``, as :func:`build_cell` recorded it."""
    warmest = f"{cell}_{_temp_tag(max(ambients))}"
    return float(json.loads((workdir / f"{warmest}_ocv.json").read_text())["capacity_ah"])


def fit_cell(cell: str, ambients: Sequence[float], workdir: Path, opt: RunOptions) -> Path:
    """The issue's first command on one cell: ``socd fit`` on every ambient's US06 and the OCV tests
    of ``opt.ocv_ambients`` (default: every ambient's); a profile on disk is kept unless
    ``opt.refit``.  The capacity the fit is told is the C/20 discharge of the warmest ambient with
    an OCV test in the fit, whatever order the ambients come in."""
    profile = workdir / f"{cell}{opt.profile_tag}.toml"
    if profile.exists() and not opt.refit:
        return profile
    ocv_ambients = ambients if opt.ocv_ambients is None else opt.ocv_ambients
    capacity = told_capacity_ah(cell, ocv_ambients or ambients, workdir)
    fit_files = [str(workdir / f"{cell}_{_temp_tag(t)}_{part}.csv") for t in ambients
                 for part in ("ocv", opt.fit_drive) if part == opt.fit_drive or t in ocv_ambients]
    subprocess.run(["socd", "fit", *fit_files, "--capacity-ah", f"{capacity:.4f}", "-q", "-o", str(profile),
                    *opt.fit_flags], check=True)
    return profile


def run_cell(cell: str, ambients: Sequence[float], workdir: Path, opt: RunOptions) -> Path:
    """The issue's two commands on one cell: :func:`fit_cell`, then every drive but the fit's
    scored; returns the evaluation JSON."""
    profile = fit_cell(cell, ambients, workdir, opt)
    others = [str(workdir / f"{cell}_{_temp_tag(t)}_{d}.csv") for t in ambients for d in DRIVES if d != opt.fit_drive]
    out = workdir / f"{cell}{opt.profile_tag}{opt.tag}_eval.json"
    cmd = ["socd", "evaluate", "--cell", str(profile), *others, "-q", "--json", str(out)]
    cmd += [arg for e in opt.estimators for arg in ("--estimator", e)]
    if "ecm2rc-ekf" not in opt.estimators:
        cmd.append("--no-bar")
    if opt.settings is not None:
        cmd += ["--settings", str(opt.settings)]
    if opt.current_bias_c:
        cmd += ["--current-bias-c", f"{opt.current_bias_c:g}"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.unseen_cell", description=__doc__.split("\n\n")[0])
    ap.add_argument("command", choices=("build", "fit", "run"),
                    help="build the recordings; fit the profile only; fit (unless on disk) and score")
    ap.add_argument("--cells", default=",".join(CELLS), help=f"PyBaMM parameter sets (default {','.join(CELLS)})")
    ap.add_argument("--ambients", default="25,10,0", help="ambient temperatures, °C (default 25,10,0)")
    ap.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR, help=f"default {DEFAULT_WORKDIR}")
    ap.add_argument("--jobs", type=int, default=1, help="simulations at once (build)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hysteresis-mv", type=float, default=0.0,
                    help="half-gap of an OCV hysteresis added to every recording, mV (build; use its own --workdir)")
    ap.add_argument("--profile-tag", default="", help="suffix of the profile (and its evaluations), for fit flags (run)")
    ap.add_argument("--refit", action="store_true", help="fit again when the profile is on disk (run)")
    ap.add_argument("--estimators", default="fomiukf,ecm2rc-ekf", help="scored side by side (run)")
    ap.add_argument("--settings", type=Path, help="`socd evaluate --settings` TOML (run)")
    ap.add_argument("--current-bias-c", type=float, default=0.0, help="`socd evaluate --current-bias-c` (run)")
    ap.add_argument("--tag", default="", help="suffix of the evaluation files (run)")
    ap.add_argument("--ocv-ambients", help="the ambients whose OCV test joins the fit (run; default: every "
                    "ambient's), e.g. 25,10,0 with --ambients 40,25,10,0,-10 as the issue's held-out check has")
    ap.add_argument("--fit-drive", choices=(FIT_DRIVE, PULSE_DRIVE), default=FIT_DRIVE,
                    help="the recording fitted at every ambient (fit, run): US06 (default), or the pulse test, "
                    "then with no OCV test unless --ocv-ambients names some, and every drive scored")
    ap.add_argument("--fit-flags", default="", help="extra `socd fit` flags as one string, e.g. "
                    "--fit-flags=--no-kinetics; give --profile-tag too (run)")
    a = ap.parse_args(argv)
    cells = [c for c in a.cells.split(",") if c]
    ambients = [float(x) for x in a.ambients.split(",") if x]
    if a.command == "build":
        jobs = [(c, t, str(a.workdir), a.seed, a.hysteresis_mv / 1000.0) for c in cells for t in ambients]
        not_built = 0
        with ProcessPoolExecutor(max_workers=max(1, a.jobs)) as ex:
            for line in ex.map(_build_one, jobs):
                failed = line.startswith(NOT_BUILT)
                not_built += failed
                print(line, flush=True, file=sys.stderr if failed else sys.stdout)
        return 2 if not_built else 0
    ocv_ambients = None if a.ocv_ambients is None else tuple(float(x) for x in a.ocv_ambients.split(",") if x)
    if a.fit_drive == PULSE_DRIVE and ocv_ambients is None:
        ocv_ambients = ()
    opt = RunOptions(tuple(shlex.split(a.fit_flags)), a.profile_tag, a.refit, tuple(e for e in a.estimators.split(",") if e),
                     a.settings, a.current_bias_c, a.tag, ocv_ambients, a.fit_drive)
    step = fit_cell if a.command == "fit" else run_cell
    failed = []
    for cell in cells:
        try:
            print(f"{cell}: {step(cell, ambients, a.workdir, opt)}", flush=True)
        except subprocess.CalledProcessError as exc:  # socd said why on stderr; the other cells still run
            failed.append(cell)
            print(f"{cell}: `{' '.join(exc.cmd[:2])}` exited {exc.returncode} (its message above)", file=sys.stderr)
    return 2 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
