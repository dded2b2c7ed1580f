"""Where `socd fit`'s poor-fit refusal should sit: fits that make good profiles beside fits of bad input.

``socd fit`` refuses a temperature whose fit leaves too much of the voltage unexplained
(:meth:`service.characterisation.characterise.TemperatureFit.problem`).  That rule is only right if
it passes the fits of every cell we have, fitted as a user would, and refuses the fits of input a
user gets wrong.  This module runs both kinds as a user would (what ``socd fit`` says is kept),
then with ``--force`` where it refused, so every profile is written; it reads from each fit's
report (``socd fit --report``) every temperature's fit RMSE, the textbook 2-RC fit's and the RMS
overpotential the dynamics had to explain, and scores each profile with ``socd evaluate`` on recordings it was not fitted on, beside
the textbook 2-RC EKF.  :func:`choose_share_bar` picks the poor-fit share bar from them, and
:func:`share_bar_table` reads that choice with each cell held out.  The kinds of fit:

* *user fits*: the four shared cells as ``docs/results/characterisation.md`` fits them, and the
  PyBaMM cells of :mod:`research.unseen_cell` (OCV test + US06 per ambient; the LFP cell at 25 °C);
* *bad input*: the same PyBaMM fits told a capacity 15 % too large or 13 % too small, and the shared
  cells fitted with another cell's OCV table;
* *sensor offset*: the PyBaMM fits with their US06 voltage 20 mV high (shown, not counted by the bar).

The PyBaMM recordings carry ``soc_true``, so a wrong capacity does not move the truth they are
scored against.

    python -m research.fit_quality run [--jobs 2] [--workdir out/fit_quality] [--only NAME,...]
    python -m research.fit_quality table [--workdir out/fit_quality]
    python -m research.fit_quality capacity [--jobs 2]   # the PyBaMM fits told a capacity 0-15 % too large

Needs the recordings of ``research.unseen_cell build`` (``out/unseen_cell``, and the LFP cell's
``--cells Prada2013 --ambients 25 --workdir out/unseen_lfp``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from itertools import pairwise
from pathlib import Path

import numpy as np

from research.unseen_cell import CELLS, DRIVES, FIT_DRIVE, _temp_tag, told_capacity_ah
from research.unseen_cell import DEFAULT_WORKDIR as UNSEEN
from service.characterisation.characterise import POOR_FIT_SHARE
from service.characterisation.fit_summary import FitSummary

REAL = Path("../shared/data/real")
PAN, CALCE, A123, OCV = REAL / "panasonic_18650pf", REAL / "calce_inr18650_20r", REAL / "calce_a123", REAL / "ocv"
UNSEEN_LFP = Path("out/unseen_lfp")
DEFAULT_WORKDIR = Path("out/fit_quality")
#: the ambients the PyBaMM NMC cells are fitted and scored at (research.unseen_cell's)
PYBAMM_AMBIENTS = (25.0, 10.0, 0.0)
PAN_TEMPS = ("25C", "10C", "0C", "m10C", "m20C")
CALCE_SCORED = {"DST_50soc": 10015, "FUDS_80soc": 9999, "FUDS_50soc": 5080, "US06_50soc": 10160, "US06_80soc": 9984}
#: how far the bad-input jobs move what the user tells `socd fit`
CAPACITY_ERROR = 1.15
VOLTAGE_OFFSET_V = 0.020


@dataclass(frozen=True)
class FitJob:
    """One ``socd fit`` (run as given, then with ``--force`` where it refuses) and the recordings its
    profile is scored on."""

    name: str
    #: "user fit"; "bad input" (a rule should refuse it); "sensor offset" (the drive's voltage alone
    #: offset: it moves the fit by less than cells differ, so no bar on the fit can refuse it, and it
    #: is shown beside the bar, not counted by it)
    kind: str
    what: str
    fit_args: tuple[str, ...]
    scored: tuple[str, ...]
    evaluate_args: tuple[str, ...] = ()


@dataclass
class JobResult:
    name: str
    kind: str
    what: str
    temperatures: list[dict] = field(default_factory=list)
    #: mean SOC RMSE after 600 s per estimator over the scored recordings, %; None: not scored
    soc_rmse_pct: dict[str, float] = field(default_factory=dict)
    #: the one line `socd fit` refused with (the figures are then the ``--force`` run's)
    refused: str | None = None


def _pybamm_job(cell: str, ambients: tuple[float, ...], workdir: Path, kind: str, what: str,
                capacity_scale: float = 1.0, fit_dir: Path | None = None, suffix: str = "") -> FitJob:
    tags = [_temp_tag(t) for t in ambients]
    capacity = told_capacity_ah(cell, ambients, workdir)
    src = fit_dir or workdir
    fit = [str(workdir / f"{cell}_{t}_ocv.csv") for t in tags] + [str(src / f"{cell}_{t}_{FIT_DRIVE}.csv") for t in tags]
    scored = tuple(str(workdir / f"{cell}_{t}_{d}.csv") for t in tags for d in DRIVES if d != FIT_DRIVE)
    return FitJob(f"{cell}{suffix}", kind, what, (*fit, "--capacity-ah", f"{capacity * capacity_scale:.4f}"), scored)


def jobs(workdir: Path) -> list[FitJob]:
    """Every fit the table reads; bad-input recordings are written under ``workdir``."""
    pan_drives = tuple(str(p) for t in PAN_TEMPS for p in sorted(PAN.glob(f"pan18650pf_{t}_*.csv"))
                       if "HPPC" not in p.name and "US06" not in p.name)
    pan_us06 = tuple(str(PAN / f"pan18650pf_{t}_US06.csv") for t in PAN_TEMPS)
    calce_fit = (str(CALCE / "calce20r_25C_DST_80soc.csv"), "--full-at", "3303", "--capacity-ah", "1.999")
    calce_scored = tuple(str(CALCE / f"calce20r_25C_{n}.csv") for n in CALCE_SCORED)
    calce_eval = tuple(a for fa in CALCE_SCORED.values() for a in ("--full-at", str(fa)))
    out = [
        FitJob("panasonic_ocv_us06", "user fit", "Panasonic: OCV test + US06 per temperature",
               (str(OCV / "ocv_pan18650pf_25C.csv"), *pan_us06, "--capacity-ah", "2.77"), pan_drives),
        FitJob("panasonic_hppc", "user fit", "Panasonic: the five HPPC tests alone",
               (*(str(PAN / f"pan18650pf_{t}_HPPC.csv") for t in PAN_TEMPS), "--capacity-ah", "2.77", "--full-at", "0"),
               pan_drives + pan_us06),
        FitJob("calce", "user fit", "CALCE 20R: DST 80 % alone", calce_fit, calce_scored, calce_eval),
        FitJob("a123", "user fit", "A123: DST with its charge OCV table and --hysteresis",
               (str(A123 / "calce_a123_20C_DST.csv"), "--full-at", "4815", "--capacity-ah", "1.041", "--hysteresis",
                "--ocv", str(OCV / "ocv_a123_20C_charge_soc_table.csv")),
               (str(A123 / "calce_a123_20C_FUDS.csv"), str(A123 / "calce_a123_20C_US06.csv")),
               ("--full-at", "4478", "--full-at", "4436")),
    ]
    for cell in CELLS:
        out.append(_pybamm_job(cell, PYBAMM_AMBIENTS, UNSEEN, "user fit", f"PyBaMM {cell}: OCV test + US06 per ambient"))
    out.append(_pybamm_job("Prada2013", (25.0,), UNSEEN_LFP, "user fit", "PyBaMM Prada2013 (LFP): OCV test + US06"))
    for cell in CELLS:
        out.append(_pybamm_job(cell, PYBAMM_AMBIENTS, UNSEEN, "bad input",
                               f"PyBaMM {cell}, told a capacity {CAPACITY_ERROR - 1:.0%} too large",
                               capacity_scale=CAPACITY_ERROR, suffix="_capacity_high"))
        out.append(_pybamm_job(cell, PYBAMM_AMBIENTS, UNSEEN, "bad input",
                               f"PyBaMM {cell}, told a capacity {1 - 1 / CAPACITY_ERROR:.0%} too small",
                               capacity_scale=1.0 / CAPACITY_ERROR, suffix="_capacity_low"))
        out.append(_pybamm_job(cell, PYBAMM_AMBIENTS, UNSEEN, "sensor offset",
                               f"PyBaMM {cell}, its US06 voltage {VOLTAGE_OFFSET_V * 1000:.0f} mV high",
                               fit_dir=workdir / "offset", suffix="_voltage_offset"))
    out += [
        FitJob("calce_pan_ocv", "bad input", "CALCE 20R: DST 80 % with the Panasonic OCV table",
               (*calce_fit, "--ocv", str(OCV / "ocv_pan18650pf_25C_soc_table.csv")), calce_scored, calce_eval),
        FitJob("panasonic_a123_ocv", "bad input", "Panasonic: US06 per temperature with the A123 OCV table",
               (*pan_us06, "--capacity-ah", "2.77", "--ocv", str(OCV / "ocv_a123_20C_charge_soc_table.csv")),
               pan_drives),
    ]
    return out


def write_offset_recordings(workdir: Path) -> None:
    """The PyBaMM US06 recordings with the voltage read :data:`VOLTAGE_OFFSET_V` high."""
    from service.recording import load_recording, save_recording

    dest = workdir / "offset"
    dest.mkdir(parents=True, exist_ok=True)
    for src in sorted(UNSEEN.glob(f"*_{FIT_DRIVE}.csv")):
        target = dest / src.name
        if target.exists():
            continue
        rec = load_recording(src)
        cols = [rec.time_s, rec.current_a, rec.voltage_v + VOLTAGE_OFFSET_V, rec.temperature_c]
        save_recording(target, np.column_stack(cols), fmt="%.5f")


def fit_rows(report: Path) -> list[dict]:
    """Each temperature's figures for the profile ``socd fit --report`` says it wrote, with the
    product rule's verdict on them (``refused_by``)."""
    written = FitSummary.load(report).written()
    return [{"temp_c": t.temp_c, "rmse_mv": t.rmse_mv, "ecm_rmse_mv": t.ecm_rmse_mv,
             "ecm_simulated_mv": t.ecm_simulated_mv, "overpotential_rms_mv": t.overpotential_rms_mv,
             "unexplained_share": t.unexplained_share, "refused_by": t.problem} for t in written.temperatures]


def run_job(job: FitJob, workdir: Path) -> JobResult:
    res = JobResult(job.name, job.kind, job.what)
    profile, log, report = (workdir / f"{job.name}{end}" for end in (".toml", ".fitlog", "_fit.json"))
    for force in ((), ("--force",)):
        report.unlink(missing_ok=True)
        fit = subprocess.run(["socd", "fit", *job.fit_args, *force, "-o", str(profile), "--report", str(report)],
                             capture_output=True, text=True, check=False)
        log.write_text(fit.stdout + fit.stderr)
        if fit.returncode == 0:
            break
        res.refused = (fit.stderr.strip().splitlines() or ["(no message)"])[-1].removeprefix("socd fit: error: ")
    res.temperatures = fit_rows(report) if report.exists() else []
    if fit.returncode != 0:
        return res
    scores = workdir / f"{job.name}_eval.json"
    subprocess.run(["socd", "evaluate", "--cell", str(profile), *job.scored, *job.evaluate_args,
                    "--estimator", "fomiukf", "--estimator", "ecm2rc-ekf", "-q", "--json", str(scores)],
                   check=True, stdout=subprocess.DEVNULL)
    per: dict[str, list[float]] = {}
    for r in json.loads(scores.read_text())["results"]:
        per.setdefault(r["estimator"], []).append(r["soc_rmse_after_600s_pct"])
    res.soc_rmse_pct = {e: statistics.fmean(v) for e, v in per.items()}
    return res


def table(results: list[JobResult]) -> str:
    """One row per fitted temperature: the figures the refusal reads and what the profile then scores."""
    head = ("| fit | kind | `socd fit` | °C | fit RMSE [mV] | 2-RC fit [mV] | RMS overpotential [mV] | share left "
            "| `fomiukf` mean [%] | `ecm2rc-ekf` mean [%] |")
    lines = [head, "|" + "---|" * 10]
    for r in results:
        soc = [f"{r.soc_rmse_pct[e]:.2f}" if e in r.soc_rmse_pct else "-" for e in ("fomiukf", "ecm2rc-ekf")]
        verdict = "writes it" if r.refused is None else f"refuses: {refusal_kind(r.refused)}"
        rows = r.temperatures or [None]
        for i, t in enumerate(rows):
            figures = ("- | - | - | - | -" if t is None else f"{t['temp_c']:g} | {t['rmse_mv']:.1f} | {t['ecm_rmse_mv']:.1f} | "
                       f"{t['overpotential_rms_mv']:.0f} | {t['unexplained_share']:.2f}")
            first = i == 0
            lines.append(f"| {r.what if first else ''} | {r.kind if first else ''} | {verdict if first else ''} | "
                         f"{figures} | {soc[0] if first else ''} | {soc[1] if first else ''} |")
    return "\n".join(lines)


def refusal_kind(message: str) -> str:
    """What a ``socd fit`` refusal was about, in a few words."""
    if "RMS overpotential" in message:
        return "poor fit"
    if "textbook 2-RC fit" in message:
        return "worse than the 2-RC fit"
    if "OCV test's slow branch moved" in message:
        return "capacity above the OCV test's"
    return message


def job_cell(name: str) -> str:
    """The cell a job's recordings come from (the unit a bar is held out by)."""
    return name.split("_")[0]


def largest_share(r: JobResult) -> float:
    return max((t["unexplained_share"] for t in r.temperatures), default=float("nan"))


def share_errors(results: list[JobResult], bar: float) -> tuple[int, int]:
    """User fits the share rule alone would refuse at ``bar``, and bad inputs no rule refuses at it
    (:func:`share_judged` are the bad inputs it is judged on)."""
    user = [r for r in results if r.kind == "user fit"]
    return (sum(largest_share(r) > bar for r in user), sum(largest_share(r) <= bar for r in share_judged(results)))


def share_judged(results: list[JobResult]) -> list[JobResult]:
    """The bad inputs the share rule is judged on: those the capacity rule does not refuse first."""
    return [r for r in results if r.kind == "bad input"
            and not (r.refused and refusal_kind(r.refused) == "capacity above the OCV test's")]


def choose_share_bar(results: list[JobResult]) -> float:
    """The bar with the fewest errors of :func:`share_errors` (a user fit refused or a bad input
    written, counted alike): the middle of the widest span of bars that reach that fewest."""
    edges = sorted({round(largest_share(r), 4) for r in results if r.temperatures} | {0.0, 1.0})
    mids = [(a + b) / 2 for a, b in pairwise(edges)]
    cost = [sum(share_errors(results, m)) for m in mids]
    best = min(cost)
    spans: list[list[float]] = []
    for (a, b), c in zip(pairwise(edges), cost):
        if c != best:
            continue
        if spans and spans[-1][1] == a:  # next to the last one: one span
            spans[-1][1] = b
        else:
            spans.append([a, b])
    lo, hi = max(spans, key=lambda ab: ab[1] - ab[0])
    return (lo + hi) / 2


def share_bar_table(results: list[JobResult], product_bar: float = POOR_FIT_SHARE) -> str:
    """The bar chosen on every job, and on all but each cell's jobs with that cell's jobs read at it."""
    rows = ["| chosen on | bar | user fits refused | bad input written (of those the capacity rule lets through) |",
            "|---|---|---|---|"]
    n_user = sum(r.kind == "user fit" for r in results)
    n_bad = len(share_judged(results))
    for label, bar in (("the product's bar", product_bar), ("every job", choose_share_bar(results))):
        user, bad = share_errors(results, bar)
        rows.append(f"| {label} | {bar:.2f} | {user}/{n_user} | {bad}/{n_bad} |")
    held_user = held_bad = 0
    for cell in dict.fromkeys(job_cell(r.name) for r in results):
        inside = [r for r in results if job_cell(r.name) == cell]
        bar = choose_share_bar([r for r in results if job_cell(r.name) != cell])
        user, bad = share_errors(inside, bar)
        held_user, held_bad = held_user + user, held_bad + bad
        rows.append(f"| all but `{cell}`, read on `{cell}` | {bar:.2f} | {user}/{sum(r.kind == 'user fit' for r in inside)} "
                    f"| {bad}/{len(share_judged(inside))} |")
    rows.append(f"| **each cell held out, summed** | - | **{held_user}/{n_user}** | **{held_bad}/{n_bad}** |")
    return "\n".join(rows)


#: capacity errors of the ``capacity`` sweep (1.0: the OCV test's own discharge, as ``research.unseen_cell``)
CAPACITY_SWEEP = (1.0, 1.03, 1.05, 1.08, 1.15)


def capacity_jobs() -> list[FitJob]:
    """The PyBaMM cells' user fits told each capacity of :data:`CAPACITY_SWEEP`."""
    return [_pybamm_job(cell, PYBAMM_AMBIENTS, UNSEEN, "capacity", f"{scale:g}", capacity_scale=scale,
                        suffix=f"_capacity_x{scale:g}") for scale in CAPACITY_SWEEP for cell in CELLS]


def capacity_table(results: list[JobResult]) -> str:
    """`fomiukf`'s mean SOC RMSE against the capacity error, per cell, and what `socd fit` did."""
    by = {(r.name.split("_capacity_x")[0], r.what): r for r in results}
    lines = ["| `--capacity-ah` over the OCV test's discharge | " + " | ".join(f"`{c}`" for c in CELLS)
             + " | `socd fit` |", "|" + "---|" * (len(CELLS) + 2)]
    for scale in CAPACITY_SWEEP:
        cells = [by.get((c, f"{scale:g}")) for c in CELLS]
        soc = [f"{r.soc_rmse_pct['fomiukf']:.2f} %" if r is not None and "fomiukf" in r.soc_rmse_pct else "-"
               for r in cells]
        refusals = {refusal_kind(r.refused) for r in cells if r is not None and r.refused is not None}
        verdict = "refuses: " + ", ".join(sorted(refusals)) if refusals else "writes it"
        lines.append(f"| {scale - 1:+.0%} | " + " | ".join(soc) + f" | {verdict} |")
    return "\n".join(lines)


def load_results(summary: list[dict] | Path) -> list[JobResult]:
    """The results of a summary file (``fit_quality.json``, ``capacity_sweep.json``) or of its parsed list."""
    return [JobResult(**d) for d in (json.loads(summary.read_text()) if isinstance(summary, Path) else summary)]


def markdown(summary: list[dict] | Path) -> str:
    """The ``run`` summary as docs/results/characterisation.md shows it: :func:`table`, then
    :func:`share_bar_table`."""
    results = load_results(summary)
    return (table(results) + "\n\nThe poor-fit share bar, chosen as `research.fit_quality` chooses it (fewest user fits "
            "refused plus bad inputs written, the middle of the widest span of bars that reach it):\n\n"
            + share_bar_table(results))


def capacity_markdown(summary: list[dict] | Path) -> str:
    """The ``capacity`` summary as docs/results/characterisation.md shows it (:func:`capacity_table`)."""
    return capacity_table(load_results(summary))


def run_jobs(todo: list[FitJob], summary: Path, workdir: Path, n_jobs: int) -> list[JobResult]:
    """Run ``todo`` (``n_jobs`` at once), keeping every result in ``summary`` as it comes."""
    done = {d["name"]: d for d in json.loads(summary.read_text())} if summary.exists() else {}
    order = [j.name for j in todo]
    with ThreadPoolExecutor(max_workers=max(1, n_jobs)) as ex:
        for res in ex.map(lambda j: run_job(j, workdir), todo):
            done[res.name] = asdict(res)
            print(f"{res.name}: {res.refused or res.soc_rmse_pct}", flush=True)
            summary.write_text(json.dumps(sorted(done.values(), key=lambda d: order.index(d["name"])
                                                 if d["name"] in order else len(order)), indent=1))
    return load_results(summary)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.fit_quality", description=__doc__.split("\n\n")[0])
    ap.add_argument("command", choices=("run", "table", "capacity", "capacity-table"),
                    help="run: the user fits and bad input; capacity: the PyBaMM fits told a capacity "
                    f"{', '.join(f'{x - 1:+.0%}' for x in CAPACITY_SWEEP)} off".replace("%", "%%") + "; *-table: print a summary's table")
    ap.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    ap.add_argument("--jobs", type=int, default=1, help="fits at once (run)")
    ap.add_argument("--only", help="job names, comma-separated (run)")
    a = ap.parse_args(argv)
    a.workdir.mkdir(parents=True, exist_ok=True)
    if a.command.startswith("capacity"):
        summary = a.workdir / "capacity_sweep.json"
        results = (load_results(summary) if a.command == "capacity-table"
                   else run_jobs(capacity_jobs(), summary, a.workdir, a.jobs))
        print(capacity_table(results))
        return 0
    summary = a.workdir / "fit_quality.json"
    if a.command == "run":
        write_offset_recordings(a.workdir)
        todo = [j for j in jobs(a.workdir) if a.only is None or j.name in a.only.split(",")]
        run_jobs(todo, summary, a.workdir, a.jobs)
    print(table(load_results(summary)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
