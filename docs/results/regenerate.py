"""Rerun the commands behind ``docs/results/*.md`` and rewrite their tables from the JSON they write.

    python docs/results/regenerate.py --list                 # every table, its file and rough run time
    python docs/results/regenerate.py --only bench           # rerun one table's commands, rewrite it
    python docs/results/regenerate.py --only eval_a123 --only bench --jobs 2
    python docs/results/regenerate.py                        # every table (many hours)
    python docs/results/regenerate.py --commands-only        # rewrite the command blocks, run nothing
    python docs/results/regenerate.py --render-only --only bench   # re-render from JSON already in out/

Each results file holds, per table, two marked blocks::

    <!-- BEGIN command:NAME --> ... <!-- END command:NAME -->   the shell commands (from TABLES)
    <!-- BEGIN table:NAME -->   ... <!-- END table:NAME -->     the table and when it was produced

The command block is always written from :data:`TABLES`, so the commands shown are the ones run.
Commands run from the repository root under ``bash -euo pipefail`` with ``socd`` and ``python``
bound to this interpreter; the JSON goes to ``out/`` (relative to the root). Tables are rendered
by the tools' own table functions (``summary``, ``nested_tuning``, ``validate``...) where one
exists, so a table here and the tool's printed table cannot differ.
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib
import json
import re
import statistics
import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# the research tools (research/) live in the checkout, not in the installed package
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
RESULTS = Path(__file__).resolve().parent
OUT = Path("out")

class RegenerateError(Exception):
    """A missing marker, a failed command or a missing JSON file: one line for the user."""


def tool(name: str):
    return importlib.import_module(f"research.{name}")


# -- renderers: JSON in out/ -> markdown --------------------------------------------------------
def _read(out: Path, name: str):
    path = out / name
    if not path.is_file():
        raise RegenerateError(f"{path}: missing (run the table's commands first)")
    return json.loads(path.read_text())


def evaluate_table(*specs: str, only: str | None = None) -> Callable[[Path], str]:
    """``summary`` tables of ``socd evaluate --json`` files; ``A.json+B.json`` puts B beside A."""
    def render(out: Path) -> str:
        summary = tool("summary")
        keep = set(only.split(",")) if only else None
        tables = []
        for spec in specs:
            parts = [out / p for p in spec.split("+")]
            for p in parts:
                if not p.is_file():
                    raise RegenerateError(f"{p}: missing (run the table's commands first)")
            tables.append(summary.table("+".join(str(p) for p in parts), keep))
        return "\n\n".join(tables)
    return render


def group_table(name: str, groups: tuple[tuple[str, str], ...]) -> Callable[[Path], str]:
    """Mean and worst SOC RMSE after 600 s per estimator for each group of recordings (a regular
    expression on the recording's name), from one ``socd evaluate --json``; where the bar ran, each
    other estimator's mean difference from it with its standard error, paired by recording."""
    def render(out: Path) -> str:
        summary = tool("summary")
        rows = _read(out, name)["results"]
        estimators = list(dict.fromkeys(r["estimator"] for r in rows))
        compared = [e for e in estimators if e != summary.BAR] if summary.BAR in estimators else []
        head = ("| recordings | files | " + " | ".join(f"`{e}` mean / worst" for e in estimators)
                + "".join(f" | `{e}` − `{summary.BAR}` ± SE" for e in compared) + " |")
        lines = [head, "|" + "---|" * (2 + len(estimators) + len(compared))]
        for label, pattern in groups:
            chosen = [r for r in rows if re.search(pattern, r["recording"])
                      and r["soc_rmse_after_600s_pct"] is not None]
            if not chosen:
                continue
            by: dict[str, dict[str, dict]] = {}
            for r in chosen:
                by.setdefault(r["recording"], {})[r["estimator"]] = r
            cells = []
            for e in estimators:
                vals = [r["soc_rmse_after_600s_pct"] for r in chosen if r["estimator"] == e]
                cells.append(f"{sum(vals) / len(vals):.2f} / {max(vals):.2f}" if vals else "-")
            cells += [summary.paired_cell(summary.bar_pairs(by, e, summary.BAR)) for e in compared]
            files = len({r["recording"] for r in chosen})
            lines.append(f"| {label} | {files} | " + " | ".join(cells) + " |")
        return "\n".join(lines)
    return render


def unseen_table(folder: str, cells: tuple[str, ...] = (), tag: str = "",
                 groups: tuple[tuple[str, str], ...] = ()) -> Callable[[Path], str]:
    """:func:`group_table` by ambient for each of ``research.unseen_cell``'s cells (all unless given),
    from its run in ``out/<folder>/`` with profile tag ``tag``."""
    def render(out: Path) -> str:
        return "\n\n".join(f"`{cell}`:\n\n" + group_table(f"{folder}/{cell}{tag}_eval.json", groups or UNSEEN_GROUPS)(out)
                             for cell in cells or UNSEEN_CELLS)
    return render


def runs_table(runs: tuple[tuple[str, ...], ...], groups: tuple[tuple[str, str], ...],
               estimator: str = "fomiukf") -> Callable[[Path], str]:
    """One row per ``socd evaluate --json`` run (label, file[, estimator]), one column per group of
    recordings (a regular expression on the name): the row's estimator's (default ``estimator``) mean SOC
    RMSE after 600 s there."""
    def render(out: Path) -> str:
        lines = ["| run | " + " | ".join(label for label, _ in groups) + " |", "|---|" + "---|" * len(groups)]
        for label, name, *row_estimator in runs:
            means = group_means(out, name, groups, row_estimator[0] if row_estimator else estimator)
            cells = ["-" if m is None else f"{m:.2f}" for m in means]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        return "\n".join(lines)
    return render


def group_means(out: Path, name: str, groups: tuple[tuple[str, str], ...],
                estimator: str = "fomiukf") -> list[float | None]:
    """``estimator``'s mean SOC RMSE after 600 s in one ``socd evaluate --json`` for each group of
    recordings (a regular expression on the name); None where the group has no scored recording."""
    rows = [r for r in _read(out, name)["results"]
            if r["estimator"] == estimator and r["soc_rmse_after_600s_pct"] is not None]
    means: list[float | None] = []
    for _, pattern in groups:
        vals = [r["soc_rmse_after_600s_pct"] for r in rows if re.search(pattern, r["recording"])]
        means.append(sum(vals) / len(vals) if vals else None)
    return means


def fit_rmse_by_temperature(log: str) -> dict[str, float]:
    """The fit RMSE ``socd fit`` logged for each temperature's kept point (``[fit]   T °C: R_ohm ...
    fit RMSE X mV`` lines), keyed by the temperature as logged."""
    found = {}
    for line in log.splitlines():
        m = re.match(r"\[fit\]\s+(-?\d+(?:\.\d+)?) °C: R_ohm .*?fit RMSE ([\d.]+) mV", line)
        if m:
            found[m.group(1)] = float(m.group(2))
    return found


def seed_spread_table(runs: tuple[tuple[str, str], ...], temps: tuple[str, ...],
                      groups: tuple[tuple[str, str], ...], averaged: int = 0) -> Callable[[Path], str]:
    """One row per fit (label, path stem under ``out/`` of its ``.json`` evaluation and ``.fitlog``):
    ``fomiukf``'s mean SOC RMSE after 600 s per group of drives, then the fit RMSE its log gives
    at each temperature; with ``averaged``, after the first that many runs a row of their group means
    averaged."""
    def render(out: Path) -> str:
        head = ("| fit | " + " | ".join(f"drives {label}" for label, _ in groups) + " | "
                + " | ".join(f"fit RMSE {t} °C [mV]" for t in temps) + " |")
        rows, per_run = [], []
        for label, stem in runs:
            per_run.append(group_means(out, f"{stem}.json", groups))
            means = ["-" if m is None else f"{m:.2f}" for m in per_run[-1]]
            log = out / f"{stem}.fitlog"
            if not log.is_file():
                raise RegenerateError(f"{log}: missing (run the table's commands first)")
            rmse = fit_rmse_by_temperature(log.read_text())
            rows.append(f"| {label} | " + " | ".join(means) + " | "
                        + " | ".join(f"{rmse[t]:.1f}" if t in rmse else "-" for t in temps) + " |")
        if averaged:
            cells = [f"{sum(col) / len(col):.2f}" if None not in col else "-" for col in zip(*per_run[:averaged])]
            rows.insert(averaged, f"| mean of the {averaged} rows above | " + " | ".join(cells) + " |"
                        + " - |" * len(temps))
        return "\n".join([head, "|---|" + "---|" * (len(groups) + len(temps)), *rows])
    return render


def fit_file_rule_table(out: Path) -> str:
    """Per characterisation and temperature: ``fomiukf`` on the fit file(s) and on the held-out files
    with the fractional profile and with its 2-RC point, which of the two the fit file picks, and
    the held-out score at that pick."""
    header = ("| characterisation | temperature | fit file: fractional | fit file: 2-RC point | the fit file picks "
              "| held out: fractional | held out: 2-RC point | held out at the pick |")
    lines = [header, "|---|---|---|---|---|---|---|---|"]
    changes = []
    for label, tag, groups in FIT_FILE_CELLS:
        cols = [group_means(out, f"pt2/{tag}{part}.json", groups) for part in ("_fit", "_2rc_fit", "_held", "_2rc_held")]
        for (t, _), ff, fb, hf, hb in zip(groups, *cols):
            if None in (ff, fb, hf, hb):
                continue
            pick_2rc = fb < ff
            changes.append(hb - hf if pick_2rc else 0.0)
            lines.append(f"| {label} | {t} | {ff:.2f} | {fb:.2f} | {'2-RC point' if pick_2rc else 'fractional'} "
                         f"| {hf:.2f} | {hb:.2f} | {hb if pick_2rc else hf:.2f} |")
    moved = [c for c in changes if c != 0.0]
    lines.append(f"\nThe rule moves {len(moved)} of {len(changes)} rows: {sum(c < 0 for c in moved)} better, "
                 f"{sum(c > 0 for c in moved)} worse, held-out mean over the rows {statistics.mean(changes):+.3f} "
                 "points against the fractional profile everywhere.")
    return "\n".join(lines)


def json_rows_table(header: str, row: Callable[[str, dict], str], names: tuple[str, ...]) -> Callable[[Path], str]:
    """One row per run from its ``--json``: ``row(name, data)`` under ``header``."""
    def render(out: Path) -> str:
        lines = [header, "|" + "---|" * (header.count("|") - 1)]
        lines += [row(n, _read(out, n)) for n in names]
        return "\n".join(lines)
    return render


def bench_table(*names: str) -> Callable[[Path], str]:
    """One row per ``socd bench --json`` run."""
    return json_rows_table(
        "| run | cells | L | p | pipeline, cell-steps/s | per-cell loop, cell-steps/s | ratio |",
        lambda n, b: (f"| `{n}` | {b['cells']} | {b['memory_length']} | {b['innovation_length']} | "
                      f"{b['cell_steps_per_s']:,.0f} | {b['reference_cell_steps_per_s']:,.0f} | {b['ratio']:.0f}× |"),
        names)


def simulate_bench_table(*names: str) -> Callable[[Path], str]:
    """One row per ``socd bench --simulate --json`` run."""
    return json_rows_table(
        "| run | candidates | samples | along the recording, candidate-samples/s "
        "| stepping the model, candidate-samples/s | ratio | largest difference, V |",
        lambda n, b: (f"| `{n}` | {b['candidates']} | {b['steps']:,} | {b['samples_per_s']:,.0f} | "
                      f"{b['reference_samples_per_s']:,.0f} | {b['ratio']:.0f}× | {b['max_abs_diff_v']:.1e} |"),
        names)


def _p50_p99(p: dict) -> str:
    return "–" if not p.get("n") else f"{p['p50']:.1f} / {p['p99']:.1f}"


def latency_table(*names: str) -> Callable[[Path], str]:
    """One row per ``socd bench --latency --json`` run."""
    return json_rows_table(
        "| run | cells | rate, Hz | s | estimate p50 / p99, ms | Zenoh put p50 / p99, ms "
        "| delivered summary p50 / p99, ms | delivered last cell p50 / p99, ms | CPU, % of a core |",
        lambda n, d: (f"| `{n}` | {d['cells']} | {d['rate_hz']:g} | {d['seconds']:g} | {_p50_p99(d['estimate_ms'])} | "
                      f"{_p50_p99(d['put_ms'])} | {_p50_p99(d['delivered_summary_ms'])} | "
                      f"{_p50_p99(d['delivered_last_cell_ms'])} | {d['cpu_pct']:.0f} |"),
        names)


def demo_capacity_table(*names: str) -> Callable[[Path], str]:
    """One row per ``socd demo --json`` run: the online capacity and each cell's SOC error."""
    def row(n: str, d: dict) -> str:
        cap, rmse, std = d["capacity_err_pct"], d["per_cell_rmse_pct"], d["capacity_std_pct"]
        median = statistics.median(d["true_capacity_pct"])
        covered = sum(abs(e) <= 2 * s for e, s in zip(cap, std))
        return (f"| `{n}` | {d['cells']} | {100 * d['capacity_spread']:g} % | {median:+.2f} % | {d['seconds_replayed']:,.0f} | "
                f"{min(cap):+.2f} to {max(cap):+.2f} | {min(std):.2f}-{max(std):.2f} | {covered}/{len(cap)} | "
                f"{min(rmse):.2f}-{max(rmse):.2f} | "
                f"{'yes' if max(map(abs, cap)) <= 1.5 and max(rmse) <= 0.7 else 'no'} |")
    return json_rows_table(
        "| run | cells | capacity spread σ | median cell's capacity vs the profile's | replayed, s "
        "| capacity error per cell, % | its published σ, % | cells within 2σ | SOC RMSE per cell, % "
        "| both targets (±1.5 %, ≤ 0.7 %) |", row, names)


def capacity_bias_table(*runs: tuple[str, str]) -> Callable[[Path], str]:
    """``python -m research.capacity_bias --json`` runs side by side, one row per band of true SOC:
    the SOC offset the frozen filter's voltage innovations point to, and the absolute capacity
    estimator's error at the band's end, per run (``runs``: label, JSON name)."""
    def render(out: Path) -> str:
        data = [_read(out, n) for _, n in runs]
        labels = [label for label, _ in runs]
        lines = ["| true SOC, % | " + " | ".join(f"voltage says, % SOC ({x})" for x in labels) + " | "
                 + " | ".join(f"absolute capacity error, % ({x})" for x in labels) + " |",
                 "|" + "---|" * (1 + 2 * len(runs))]
        def cell(b: dict | None, key: str) -> str:
            return "–" if b is None else f"{b[key]:+.2f}"

        for lo, hi in [(b["soc_from_pct"], b["soc_to_pct"]) for b in data[0]["bands"]]:
            rows = [next((b for b in d["bands"] if (b["soc_from_pct"], b["soc_to_pct"]) == (lo, hi)), None) for d in data]
            lines.append(f"| {lo:.0f}-{hi:.0f} | " + " | ".join(cell(b, "voltage_soc_offset_pct") for b in rows) + " | "
                         + " | ".join(cell(b, "absolute_capacity_err_pct") for b in rows) + " |")
        lines.append("| **whole drive** | " + " | ".join(f"**{d['voltage_soc_offset_pct']:+.2f}**" for d in data) + " | "
                     + " | ".join(f"**{d['absolute_capacity_err_pct']:+.2f}**" for d in data) + " |")
        return "\n".join(lines)
    return render


def demo_table(*names: str) -> Callable[[Path], str]:
    """One row per ``socd demo --json`` run."""
    def row(n: str, d: dict) -> str:
        lat = d["latency_ms"]
        return (f"| `{n}` | {d['cells']} | {d['speed']:g} | {d['frames_in']:,} | {d['frames_rejected']} | "
                f"{d['frames_per_s']:,.0f} | {d['cpu_pct']:.0f} | {lat.get('estimate_p50')} / "
                f"{lat.get('estimate_p99')} | {lat.get('publish_p50')} / {lat.get('publish_p99')} | "
                f"{d['soc_rmse_pct']:.2f} |")
    return json_rows_table(
        "| run | cells | speed | frames | rejected | frames/s | CPU, % of a core | estimate p50 / p99, ms "
        "| Zenoh put p50 / p99, ms | SOC RMSE, % |", row, names)


def nested_table(name: str) -> Callable[[Path], str]:
    """``nested_tuning``'s own table from its ``--json``."""
    def render(out: Path) -> str:
        d = _read(out, name)
        return tool("nested_tuning").markdown(d["values"], d["conditions"], d["estimators"], d.get("paired"),
                                              d.get("reference"))
    return render


def ocv_flat_table(profiles: tuple[tuple[str, str], ...]) -> Callable[[Path], str]:
    """Per profile (label, TOML under ``out/``): the share of SOC where the fractional profile's OCV and
    its stored 2-RC fit's OCV are flat (:func:`service.cell.ocv.flat_share`), at each row's temperature."""
    def render(out: Path) -> str:
        from service.cell.ocv import FLAT_SLOPE_V, flat_share
        from service.cell.profile import load_profile
        lines = ["| profile | OCV table | flat share at each of the table's temperatures |", "|---|---|---|"]
        for label, path in profiles:
            prof = load_profile(out / path)
            for kind, spec, table in (("fractional", prof.ocv, prof.ocv_table()),
                                      ("2-RC", prof.ecm2rc.ocv, prof.ecm2rc.ocv_table())):
                shares = [f"{t:g} °C {100 * flat_share(table, t):.0f} %" for t in sorted(spec.temps_c, reverse=True)]
                lines.append(f"| {label} | {kind} | " + ", ".join(shares) + " |")
        return (f"Share of SOC where each OCV table is flat (slope below {FLAT_SLOPE_V:g} V per unit SOC):\n\n"
                + "\n".join(lines))
    return render


def rest_check_table(*names: str) -> Callable[[Path], str]:
    """``rest_check``'s own table per ``--json``, each headed by its profile."""
    def render(out: Path) -> str:
        rc = tool("rest_check")
        parts = []
        for n in names:
            d = _read(out, n)
            parts.append(f"`{n}` (`{d['cell']}`)\n\n" + rc.markdown([rc.RestReading(**r) for r in d["rests"]]))
        return "\n\n".join(parts)
    return render


def validate_table(name: str, levels: str = "subtle,moderate,clear") -> Callable[[Path], str]:
    """The own-model grid's table from ``validate --json``."""
    def render(out: Path) -> str:
        v = tool("validate")
        rows = [v.Row(**r) for r in _read(out, name)]
        named = [r for r in rows if r.effect != "none"]
        clean = [r for r in rows if r.effect == "none"]
        return (v.table(rows, levels.split(",")) + f"\n\nnamed right: {sum(r.right for r in named)}/{len(named)}; "
                f"clean named as an effect: {sum(not r.right for r in clean)}/{len(clean)}")
    return render


def pybamm_table(name: str) -> Callable[[Path], str]:
    """The PyBaMM stand-in's table from ``validate_pybamm --json`` (rows and not-simulated recordings)."""
    def render(out: Path) -> str:
        vp = tool("validate_pybamm")
        doc = _read(out, name)
        rows = [vp.Row(**r) for r in doc if "error" not in r]
        return vp.table(rows, [r for r in doc if "error" in r])
    return render


def clean_twin_table(name: str) -> Callable[[Path], str]:
    def render(out: Path) -> str:
        ct = tool("clean_twin")
        return ct.table([ct.TwinRow.from_json(d) for d in _read(out, name)])
    return render


def devset_table(name: str) -> Callable[[Path], str]:
    """The development set's leave-one-cell-out report from ``devset rules --json``."""
    def render(out: Path) -> str:
        return tool("devset").markdown(_read(out, name))
    return render


def devset_summary_table(name: str) -> Callable[[Path], str]:
    """The held-out rows, the pooled line and the rule chosen on all cells of a ``devset rules --json``
    report (the rest of it as :func:`devset_table` renders it)."""
    def render(out: Path) -> str:
        lines = tool("devset").markdown(_read(out, name)).splitlines()
        end = next(k for k, line in enumerate(lines) if line.startswith("**Pooled"))
        chosen = [line.replace("(the product's default)", "in this grid") for line in lines
                  if line.startswith("Rule chosen on all cells")]
        return "\n".join(lines[:end + 1] + [""] + chosen)
    return render


def roundtrip_table(name: str) -> Callable[[Path], str]:
    def render(out: Path) -> str:
        rt = tool("roundtrip")
        return rt.table([rt.RoundTrip(**d) for d in _read(out, name)])
    return render


def diagnose_table(pattern: str, stems: tuple[str, ...], labels: str | None = None) -> Callable[[Path], str]:
    """One row per ``socd diagnose --json`` file ``pattern.format(stem)``: verdict, assessment, the top
    candidate's held-out RMSE before → after and gain, its split and the run time; with ``labels`` (a
    ``labels.json``) also the labelled truth."""
    def render(out: Path) -> str:
        truth = json.loads((ROOT / labels).read_text()) if labels else {}
        head = ["recording"] + (["truth"] if labels else []) + [
            "verdict", "assessment", "top effect", "held-out RMSE before → after, mV", "gain", "significant",
            "split", "run time, s"]
        lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
        for stem in stems:
            d = _read(out, pattern.format(stem))
            top = d["effects"][0] if d["effects"] else None
            cells = [stem] + ([truth.get(stem, {}).get("effect", "?")] if labels else []) + [
                f"**{d['verdict']}**", d.get("assessment", {}).get("state", "-")]
            if top is None:
                cells += ["-"] * 5
            else:
                cells += [top["name"], f"{top['rmse_before_mv']:.2f} → {top['rmse_after_mv']:.2f}",
                          f"{100 * top['score']:+.1f} %", "yes" if top["significant"] else "no", top["split"]]
            lines.append("| " + " | ".join(cells + [f"{d['seconds']:.1f}"]) + " |")
        return "\n".join(lines)
    return render


# -- the tables ----------------------------------------------------------------------------------
REAL = "D=../shared/data/real; P=$D/panasonic_18650pf; C=$D/calce_inr18650_20r; A=$D/calce_a123\n"
PAN25 = "$(ls $P/pan18650pf_25C_*.csv | grep -v HPPC)"
PANCOLD = "$(ls $P/pan18650pf_{10C,0C,m10C,m20C}_*.csv | grep -v HPPC)"
CALCE = ("$C/calce20r_25C_{DST_50soc,FUDS_80soc,FUDS_50soc,US06_50soc,US06_80soc}.csv \\\n"
         "    --full-at 10015 --full-at 9999 --full-at 5080 --full-at 10160 --full-at 9984")
A123 = "$A/calce_a123_20C_{FUDS,US06}.csv --full-at 4478 --full-at 4436"
#: recordings the leave-one-cell-out tables score but choose nothing on (DESIGN §7: the Panasonic 10 °C
#: `trise` files, whose coulomb-counted truth disagrees with the OCV at rest, are reported in their own row)
TUNING_EXCLUDE = "_10C_trise"
#: the four characterisations the leave-one-cell-out tables score (profile, JSON tag, recordings); the
#: shell variable PANX holds the Panasonic drive cycles
LOCO_CELLS = (("calce", "calce", CALCE), ("a123", "a123", A123), ("pan_hppc", "panhppc", "$PANX"),
              ("pan_us06", "panus06", "$(echo $PANX | tr ' ' '\\n' | grep -v US06)"))


def loco_sweep(field: str, tag: str, values: tuple[str, ...], default: str, *, fixed: str = "",
               reference: str | None = None, unseen: bool = False) -> str:
    """A pipeline setting swept leave-one-cell-out as ``loco_defaults`` scores (the default's runs
    are its ``noslow`` ones); the table is ``out/loco_<field's table name>.json``.  ``fixed``: settings
    lines written before the swept one in every settings file; ``reference``: the default's column
    label (``tag + default`` unless given); ``unseen``: also score ``research.unseen_cell``'s three
    cells and pool them as three more (the table ``out/loco_<name>_unseen.json``)."""
    name = {"cn": "current_noise", "vn": "voltage_noise", "ip": "identifier_prior", "ro": "model_error_shape",
            "fr": "model_error_fit", "oe": "ocv_error", "ua": "ukf_alpha"}[tag]
    reference = reference or tag + default
    vals = " ".join(values)
    json_pattern = "out/cn/{cell}_" + tag + "${{c}}_b$b.json"
    nl = "\n"
    return REAL + f"""\
mkdir -p out/cn   # the default ({default}) is loco_defaults' noslow run
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
for c in {vals}; do printf "{fixed}{field} = $c\\n" > out/cn/{tag}$c.toml; for b in 0 0.01; do
  E="--estimator fomiukf --no-bar --settings out/cn/{tag}$c.toml --current-bias-c $b -q"
{loco_evaluations(json_pattern)}{unseen_runs(f"out/cn/{tag}$c.toml", tag + "${c}", before=nl) if unseen else ""}
done; done
G=""; for b in 0 0.01; do
{loco_inputs(reference, "out/loco/{cell}_noslow_b$b.json")}{unseen_inputs(reference, "noslow", indent="  ", before=nl) if unseen else ""}
  for c in {vals}; do
{loco_inputs(tag + "$c", json_pattern, indent="    ")}{unseen_inputs(tag + "$c", tag + "${c}", before=nl) if unseen else ""}; done; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference {reference} --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_{name}{"_unseen" if unseen else ""}.json"""


def loco_ekf_sweep(field: str, tag: str, values: tuple[str, ...], default: str, name: str) -> str:
    """An ``[ecm2rc_ekf]`` tuning field swept leave-one-cell-out on the ``char_*`` profiles, every value
    (the default's too) scored here; the table is ``out/<name>.json``."""
    vals = " ".join(values)
    json_pattern = "out/cn/{cell}_" + tag + "${{c}}_b$b.json"
    return REAL + f"""\
mkdir -p out/cn
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
for c in {vals}; do printf "[ecm2rc_ekf]\\n{field} = $c\\n" > out/cn/{tag}$c.toml; for b in 0 0.01; do
  E="--estimator ecm2rc-ekf --settings out/cn/{tag}$c.toml --current-bias-c $b -q"
{loco_evaluations(json_pattern)}
done; done
G=""; for c in {vals}; do for b in 0 0.01; do
{loco_inputs(tag + "$c", json_pattern)}; done; done
python -m research.nested_tuning --by cell --estimator ecm2rc-ekf --reference {tag}{default} --exclude {TUNING_EXCLUDE} $G \\
    --json out/{name}.json"""


def loco_inputs(label: str, json_pattern: str, indent: str = "  ", named: bool = False) -> str:
    """The two lines that add one setting's four JSON (``json_pattern`` with ``{cell}`` for each
    characterisation's tag) to ``$G`` under ``label``, the two Panasonic profiles as one cell;
    ``named``: CALCE and A123 named too (a setting scored on profiles of its own)."""
    calce, a123, hppc, us06 = (json_pattern.format(cell=tag) for _, tag, _ in LOCO_CELLS)
    c, a = ("@calce", "@a123") if named else ("", "")
    return (f'{indent}G="$G {label}={calce}{c} {label}={a123}{a}"\n'
            f'{indent}G="$G {label}={hppc}@panasonic {label}={us06}@panasonic"')


def loco_evaluations(json_pattern: str, profile_pattern: str = "out/s25/{profile}.toml") -> str:
    """The scoring runs of a leave-one-cell-out table, one per characterisation, with the evaluate
    options in ``$E``; ``json_pattern`` names each JSON with ``{cell}`` for its tag, and
    ``profile_pattern`` each profile with ``{profile}`` for its name (default: the char_* tables')."""
    return "\n".join(f"  socd evaluate --cell {profile_pattern.format(profile=profile)} {files} $E "
                     f"--json {json_pattern.format(cell=tag)}" for profile, tag, files in LOCO_CELLS)
def unseen_runs(settings: str, tag: str, indent: str = "  ", before: str = "", refit: str = "") -> str:
    """``research.unseen_cell``'s scoring runs of its three cells with ``settings`` (a TOML path) at the
    current bias ``$b``: the 25 °C drives and the colder ones, each into its own JSON.  ``refit``:
    ``socd fit`` flags of a profile of their own, tagged ``_<tag>`` (fitted before the first run)."""
    run = f"python -m research.unseen_cell run --estimators fomiukf --settings {settings} --current-bias-c $b"
    fit = ""
    if refit:
        run += f" --profile-tag _{tag}"
        fit = (f'{indent}[ $b = 0 ] && python -m research.unseen_cell fit --profile-tag _{tag} --refit '
               f'--fit-flags="{refit}"\n')
    label = "" if refit else f"_{tag}"
    return (f"{before}{fit}{indent}{run} --ambients 25 --tag {label}_b$b\n"
            f"{indent}{run} --ambients 10,0 --tag {label}_b${{b}}_cold")


def unseen_inputs(label: str, tag: str, indent: str = "    ", before: str = "", named: bool = False) -> str:
    """The line that adds :func:`unseen_runs`' JSON of each unseen cell to ``$G`` under ``label``;
    ``named``: each file names its cell (a setting scored on profiles of its own)."""
    files = " ".join(f"{label}=out/unseen_cell/{cell}_{tag}_b${{b}}{part}_eval.json" + (f"@{cell}" if named else "")
                     for cell in UNSEEN_CELLS for part in ("", "_cold"))
    return f'{before}{indent}G="$G {files}"'


PAN_FIT = ("socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{25C,10C,0C,m10C,m20C}_HPPC.csv \\\n"
           "    --capacity-ah 2.77 --min-order 0.5 --max-seconds 150")
CALCE_FIT = "socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 --max-seconds 90 --no-kinetics"
#: the Panasonic recordings by temperature; the 10 °C `trise` files in their own row (DESIGN §7)
PAN_GROUPS = (("25 °C", r"_25C_"), ("10 °C (not `trise`)", r"_10C_(?!trise)"),
              ("10 °C `trise` (truth caveat)", r"_10C_trise"), ("0 °C", r"_0C_"), ("−10 °C", r"_m10C_"),
              ("−20 °C", r"_m20C_"))
LABELLED = ("dst_s101_4e4041", "hppc_s102_131537", "bjdst_s103_55f05a", "randomwalk_s104_e90722",
            "hppc_s105_437525", "dst_s106_462959", "randomwalk_s107_cac951")
REAL_DIAG = ("pan18650pf_m20C_trise_Cycle1", "pan18650pf_m20C_trise_Cycle1_soc0", "pan18650pf_10C_trise_Cycle1",
             "calce_a123_20C_DST")


#: the sample_period table's columns: the one 10 Hz drive nobody fitted on, then the 1 s drives by ambient
SAMPLE_PERIOD_GROUPS = (("25 °C `LA92` at 10 Hz", r"_10Hz"), ("25 °C, 1 s", r"_25C_(?!.*10Hz)"),
                        ("10 °C (not `trise`)", r"_10C_(?!trise)"), ("0 °C", r"_0C_"), ("−10 °C", r"_m10C_"),
                        ("−20 °C", r"_m20C_"))
#: research.unseen_cell's PyBaMM cells and their recordings by ambient
UNSEEN_CELLS = ("Chen2020", "Mohtat2020", "Marquis2019")
UNSEEN_GROUPS = (("25 °C", r"_25C_"), ("10 °C", r"_10C_"), ("0 °C", r"_0C_"))
UNSEEN_M10_GROUPS = UNSEEN_GROUPS + (("−10 °C", r"_m10C_"),)
#: PyBaMM sets beyond research.unseen_cell's default three, scored at 25 and 10 °C (``unseen_cell_more``)
MORE_UNSEEN_CELLS = ("Ai2020", "OKane2022", "Ecker2015")
#: PyBaMM sets first simulated after the defaults were chosen, a rehearsal of the held-out check (``unseen_blind``):
#: Ramadass2004 is scored at 40 and 25 °C: PyBaMM's solution of its C/20 OCV test at 10 °C runs past the cut-off,
#: and at 0 °C its US06 reaches the cut-off within 321 s
BLIND_CELLS = ("NCA_Kim2011", "Ramadass2004")
BLIND_GROUPS = (("40 °C", r"_40C_"),) + UNSEEN_GROUPS
#: the characterisations ``two_rc_point_by_fit_file`` scores: (label, tag, temperature groups)
PAN_TEMPS = (("25 °C", r"_25C_"), ("10 °C", r"_10C_"), ("0 °C", r"_0C_"), ("−10 °C", r"_m10C_"), ("−20 °C", r"_m20C_"))
FIT_FILE_CELLS = (("CALCE, DST file", "calce", (("25 °C", r"calce20r"),)),
                  ("A123, DST file", "a123", (("20 °C", r"a123"),)),
                  ("Panasonic, HPPC alone", "pan_hppc", PAN_TEMPS),
                  ("Panasonic, OCV test + US06", "pan_us06", PAN_TEMPS)) + tuple(
    (f"`{c}`, OCV test + US06", c, UNSEEN_GROUPS) for c in UNSEEN_CELLS)
#: the CALCE files by rest: the two that rest two hours at 50 % SOC, the other three, all five
#: the five CALCE 20R files scored at 25 °C, as one group
CALCE_ALL = (("CALCE 20R, 25 °C (five files)", r"calce20r"),)
#: the two A123 files scored at 20 °C, as one group
A123_ALL = (("A123, 20 °C (`FUDS`, `US06`)", r"calce_a123"),)
CALCE_REST_GROUPS = (("`DST_50soc`, `FUDS_50soc` (2 h rest at 50 %)", r"(DST|FUDS)_50soc"),
                     ("the other three", r"_80soc|US06_50soc"), ("all five", r"calce20r"))
#: loco_ocv_error's runs without the offset: (label, folder under out/, JSON tag)
OCV_ERROR_RUNS = (("off (default)", "loco", "noslow"), ("0.01 V", "cn", "oe0.01"), ("0.02 V", "cn", "oe0.02"))


def sweep_head(name: str, field: str, folder: str, tag: str) -> str:
    """The opening of a shell function ``NAME VALUE BIAS`` that scores one pipeline setting: its settings
    file under ``out/<folder>/`` and the three shared cells' evaluations (``filter_on_two_rc_model``'s
    CALCE and A123 profiles, ``loco_pure_ohmic``'s Panasonic HPPC-alone one); the caller adds its other
    cells and the closing brace."""
    return f"""\
{name}() {{  # VALUE BIAS: every profile scored with {field} = VALUE, current offset BIAS x 1C
  printf "{field} = $1\\n" > out/{folder}/{tag}$1.toml
  E="--estimator fomiukf --no-bar --settings out/{folder}/{tag}$1.toml --current-bias-c $2 -q"
  socd evaluate --cell out/s25/calce_f2.toml {CALCE} $E --json out/{folder}/calce_{tag}$1_b$2.json
  socd evaluate --cell out/s25/a123_f2.toml {A123} $E --json out/{folder}/a123_{tag}$1_b$2.json
  socd evaluate --cell out/s25/pan_hppc_pure0.toml $PANX $E --json out/{folder}/pan_{tag}$1_b$2.json
"""


@dataclass(frozen=True)
class Table:
    name: str
    doc: str  # file under docs/results/
    script: str  # shell text as a user types it, run from the repository root
    render: Callable[[Path], str] | None  # None: commands only (e.g. the profiles every table reads)
    minutes: float  # rough run time on one free core
    tags: tuple[str, ...] = field(default=())


#: the HPPC-alone fit of the Panasonic cell at one seed, scored on its drives (hppc_seed_spread*)
SEED_FIT = """\
mkdir -p out/seeds
PANX="$(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v -e HPPC -e trise)"
seed_fit() {  # NAME SEED FIT-FLAGS...: the HPPC-alone fit at one seed (its log kept), scored on the drives
  n=$1; s=$2; shift 2
  socd fit $P/pan18650pf_{25C,10C,0C,m10C,m20C}_HPPC.csv --capacity-ah 2.77 --full-at 0 --seed $s --candidates 1 "$@" \\
      -o out/seeds/$n.toml > out/seeds/$n.fitlog 2>&1
  socd evaluate --cell out/seeds/$n.toml $PANX --estimator fomiukf --no-bar -q --json out/seeds/$n.json
}
"""
SEED_TEMPS = ("25", "10", "0", "-10", "-20")
SEED_GROUPS = (("25 °C", r"_25C_"), ("10 °C", r"_10C_"), ("0 °C", r"_0C_"), ("−10 °C", r"_m10C_"),
               ("−20 °C", r"_m20C_"))


TABLES: tuple[Table, ...] = (
    Table("profiles", "soc_accuracy.md", REAL + f"""\
{PAN_FIT} --kinetics -o configs/cells/panasonic_18650pf.toml
{PAN_FIT} --no-kinetics -o configs/cells/panasonic_18650pf_nokinetics.toml
{CALCE_FIT} --no-rest-anchor -o configs/cells/calce_inr18650_20r.toml   # no OCV test: joint OCV fit
socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis \\
    --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv --max-seconds 90 --no-kinetics -o configs/cells/calce_a123.toml
{CALCE_FIT} --no-rest-anchor --slow-branch -o configs/cells/calce_inr18650_20r_slow.toml
{CALCE_FIT} --rest-anchor -o configs/cells/calce_inr18650_20r_anchored.toml""", None, 20),
    Table("profiles_refit", "soc_accuracy.md", REAL + f"""\
mkdir -p out/refit
{PAN_FIT} --kinetics -q -o out/refit/panasonic_18650pf.toml
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
socd evaluate --cell configs/cells/panasonic_18650pf.toml $PANX --estimator fomiukf -q --json out/refit/eval_committed.json
socd evaluate --cell out/refit/panasonic_18650pf.toml $PANX --estimator fomiukf -q --json out/refit/eval_refit.json""",
          lambda out: "\n\n".join(f"{label}:\n\n" + group_table(f"refit/{name}.json", PAN_GROUPS)(out) for label, name in (
              ("The committed profile (its `ecm2rc-ekf` reads the fractional parameters: no 2-RC fit is stored)",
               "eval_committed"),
              ("The profile today's `socd fit` writes (its `ecm2rc-ekf` runs on the stored 2-RC fit)", "eval_refit"))),
          25),
    Table("eval_pan25", "soc_accuracy.md", REAL + f"""\
socd evaluate --cell configs/cells/panasonic_18650pf.toml {PAN25} --json out/eval_pan25.json
socd evaluate --cell configs/cells/panasonic_18650pf_nokinetics.toml {PAN25} \\
    --estimator ecm2rc-ekf --json out/eval_pan25_nokin.json""",
          evaluate_table("eval_pan25.json+eval_pan25_nokin.json"), 25),
    Table("eval_calce", "soc_accuracy.md", REAL + f"socd evaluate --cell configs/cells/calce_inr18650_20r.toml {CALCE} \\\n"
          "    --json out/eval_calce.json", evaluate_table("eval_calce.json"), 8),
    Table("eval_a123", "soc_accuracy.md", REAL + f"socd evaluate --cell configs/cells/calce_a123.toml {A123} --json out/eval_a123.json",
          evaluate_table("eval_a123.json"), 3),
    Table("eval_pancold", "cold.md", REAL + f"""\
socd evaluate --cell configs/cells/panasonic_18650pf.toml {PANCOLD} \\
    --estimator fomiukf --estimator foukf --estimator ecm2rc-ekf --estimator coulomb --json out/eval_pancold.json
socd evaluate --cell configs/cells/panasonic_18650pf_nokinetics.toml {PANCOLD} \\
    --estimator ecm2rc-ekf --json out/eval_pancold_nokin.json""",
          evaluate_table("eval_pancold.json+eval_pancold_nokin.json"), 90),
    Table("eval_pancold_nokin_pipeline", "cold.md", REAL + f"""\
socd evaluate --cell configs/cells/panasonic_18650pf_nokinetics.toml {PANCOLD} \\
    --estimator fomiukf --estimator foukf --json out/eval_pancold_nokin_pipeline.json""",
          evaluate_table("eval_pancold_nokin_pipeline.json"), 60),
    Table("rest_check_pan", "cold.md", REAL + """\
python -m research.rest_check --cell configs/cells/panasonic_18650pf.toml \\
    $(ls $P/pan18650pf_*.csv | grep -v HPPC) --json out/rest_check_pan.json""",
          rest_check_table("rest_check_pan.json"), 2),
    Table("eval_calce_slow", "cell_options.md", REAL + f"""\
socd evaluate --cell configs/cells/calce_inr18650_20r_slow.toml {CALCE} \\
    --json out/eval_calce_slow.json
socd evaluate --cell configs/cells/calce_inr18650_20r.toml {CALCE} \\
    --json out/eval_calce.json""",
          evaluate_table("eval_calce_slow.json+eval_calce.json", only="fomiukf,foukf,ecm2rc-ekf"), 16),
    Table("rest_check_calce", "cell_options.md", REAL + """\
F="--full-at 10015 --full-at 9999 --full-at 5080 --full-at 10160 --full-at 9984"
for p in calce_inr18650_20r calce_inr18650_20r_slow calce_inr18650_20r_anchored; do
  python -m research.rest_check --cell configs/cells/$p.toml \\
      $C/calce20r_25C_{DST_50soc,FUDS_80soc,FUDS_50soc,US06_50soc,US06_80soc}.csv $F --json out/rest_check_$p.json
done""",
          rest_check_table("rest_check_calce_inr18650_20r.json", "rest_check_calce_inr18650_20r_slow.json",
                           "rest_check_calce_inr18650_20r_anchored.json"), 1),
    Table("eval_calce_anchored", "cell_options.md", REAL + f"""\
socd evaluate --cell configs/cells/calce_inr18650_20r_anchored.toml {CALCE} \\
    --json out/eval_calce_anchored.json
socd evaluate --cell configs/cells/calce_inr18650_20r.toml {CALCE} \\
    --json out/eval_calce.json""",
          evaluate_table("eval_calce_anchored.json+eval_calce.json", only="fomiukf,foukf,fom-single-scale,ecm2rc-ekf"),
          16),
    Table("eval_calce_warm", "cell_options.md", REAL + f"""\
socd evaluate --warm-start --cell configs/cells/calce_inr18650_20r_slow.toml {CALCE} \\
    --json out/eval_calce_slow_warm.json
socd evaluate --warm-start --cell configs/cells/calce_inr18650_20r.toml {CALCE} \\
    --json out/eval_calce_warm.json
socd evaluate --warm-start --cell configs/cells/calce_a123.toml {A123} --json out/eval_a123_warm.json""",
          evaluate_table("eval_calce_slow_warm.json+eval_calce_warm.json", "eval_a123_warm.json",
                         only="fomiukf,foukf,fom-single-scale,ecm2rc-ekf"), 20),
    Table("eval_pan_socr", "cell_options.md", REAL + f"""\
{PAN_FIT} --kinetics --soc-resistance -o out/pan_socr.toml
socd evaluate --cell out/pan_socr.toml {PAN25} --json out/eval_pan25_socr.json
socd evaluate --cell out/pan_socr.toml {PANCOLD} \\
    --estimator fomiukf --estimator foukf --estimator ecm2rc-ekf --estimator coulomb --json out/eval_pancold_socr.json""",
          evaluate_table("eval_pan25_socr.json", "eval_pancold_socr.json"), 130),
    Table("eval_pan25_slow", "cell_options.md", REAL + f"""\
{PAN_FIT} --kinetics --slow-branch -o out/pan_slow.toml
socd evaluate --cell out/pan_slow.toml {PAN25} --estimator fomiukf --estimator foukf --json out/eval_pan25_slow.json""",
          evaluate_table("eval_pan25_slow.json"), 25),
    Table("eval_a123_charge", "cell_options.md", REAL + f"""\
socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis --ocv-branch charge \\
    --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv --max-seconds 90 --no-kinetics -o out/a123_charge.toml
socd evaluate --cell out/a123_charge.toml {A123} --json out/eval_a123_charge.json
socd evaluate --warm-start --cell out/a123_charge.toml {A123} --json out/eval_a123_charge_warm.json""",
          evaluate_table("eval_a123_charge.json", "eval_a123_charge_warm.json"), 8),
    Table("nested_both", "tuning.md", REAL + f"""\
mkdir -p out/tune
for b in 0 0.01 -0.01; do for q in 1e-4 2e-4 5e-4 1e-3 2e-3 5e-3 1e-2; do
  printf "branch_noise_v_per_sqrt_s = $q\\n[ecm2rc_ekf]\\nu_noise_v_per_sqrt_s = $q\\n" > out/tune/rw_${{q}}_b$b.toml
  E="--estimator fomiukf --estimator ecm2rc-ekf --settings out/tune/rw_${{q}}_b$b.toml --current-bias-c $b --quiet"
  socd evaluate --cell configs/cells/panasonic_18650pf.toml {PAN25} $E --json out/tune/rw_pan_${{q}}_b$b.json
  socd evaluate --cell configs/cells/calce_inr18650_20r.toml {CALCE} $E --json out/tune/rw_calce_${{q}}_b$b.json
  socd evaluate --cell configs/cells/calce_a123.toml {A123} $E --json out/tune/rw_a123_${{q}}_b$b.json
done; done
G=""; for q in 1e-4 2e-4 5e-4 1e-3 2e-3 5e-3 1e-2; do for c in pan calce a123; do for b in 0 0.01 -0.01; do
  G="$G $q=out/tune/rw_${{c}}_${{q}}_b$b.json"; done; done; done
python -m research.nested_tuning --estimator fomiukf --estimator ecm2rc-ekf $G --json out/nested_both.json""",
          nested_table("nested_both.json"), 600),
    Table("nested2d", "tuning.md", REAL + f"""\
mkdir -p out/tune   # needs the rw_ files of nested_both
for b in 0 0.01 -0.01; do for v in cn0.05_q1e-4 cn0.05_q5e-4 cn0.05_q2e-3 cn0.1_q1e-4 cn0.1_q5e-4 cn0.1_q2e-3 cn0.2_q1e-4 cn0.4_q1e-4; do
  a=${{v#cn}}; a=${{a%_q*}}; q=${{v#*_q}}
  printf "current_noise_a = $a\\nbranch_noise_v_per_sqrt_s = $q\\n" > out/tune/g2_${{v}}_b$b.toml
  E="--estimator fomiukf --no-bar --settings out/tune/g2_${{v}}_b$b.toml --current-bias-c $b --quiet"
  socd evaluate --cell configs/cells/panasonic_18650pf.toml {PAN25} $E --json out/tune/g2_pan_${{v}}_b$b.json
  socd evaluate --cell configs/cells/calce_inr18650_20r.toml {CALCE} $E --json out/tune/g2_calce_${{v}}_b$b.json
  socd evaluate --cell configs/cells/calce_a123.toml {A123} $E --json out/tune/g2_a123_${{v}}_b$b.json
done; done
G=""; for c in pan calce a123; do for b in 0 0.01 -0.01; do for q in 1e-4 5e-4 2e-3; do G="$G cn0.02_q$q=out/tune/rw_${{c}}_${{q}}_b$b.json"
  for a in 0.05 0.1; do G="$G cn${{a}}_q$q=out/tune/g2_${{c}}_cn${{a}}_q${{q}}_b$b.json"; done; done
  for a in 0.2 0.4; do G="$G cn${{a}}_q1e-4=out/tune/g2_${{c}}_cn${{a}}_q1e-4_b$b.json"; done; done; done
python -m research.nested_tuning --estimator fomiukf $G --json out/nested2d.json""",
          nested_table("nested2d.json"), 400, ("needs:nested_both",)),
    Table("nested_bias", "tuning.md", REAL + f"""\
mkdir -p out/tune   # needs the rw_ files of nested_both
for s0 in 0.002 0.005; do for b in 0 0.01 -0.01; do
  printf "current_bias_state = true\\ncurrent_bias_init_std_c = $s0\\n" > out/tune/bs_$s0.toml
  E="--estimator fomiukf --no-bar --settings out/tune/bs_$s0.toml --current-bias-c $b --quiet"
  socd evaluate --cell configs/cells/panasonic_18650pf.toml {PAN25} $E --json out/tune/bs_pan_${{s0}}_b$b.json
  socd evaluate --cell configs/cells/calce_inr18650_20r.toml {CALCE} $E --json out/tune/bs_calce_${{s0}}_b$b.json
  socd evaluate --cell configs/cells/calce_a123.toml {A123} $E --json out/tune/bs_a123_${{s0}}_b$b.json
done; done
G=""; for c in pan calce a123; do for b in 0 0.01 -0.01; do G="$G off=out/tune/rw_${{c}}_1e-4_b$b.json"
  for s0 in 0.002 0.005; do G="$G on_$s0=out/tune/bs_${{c}}_${{s0}}_b$b.json"; done; done; done
python -m research.nested_tuning --estimator fomiukf $G --json out/nested_bias.json""",
          nested_table("nested_bias.json"), 100, ("needs:nested_both",)),
    Table("loco_defaults", "tuning.md", REAL + f"""\
mkdir -p out/loco   # the profiles are the char_* tables' (out/s25/)
printf "slow_identifier = true\\n" > out/loco/both_ids.toml
printf "fast_identifier = false\\nslow_identifier = false\\n" > out/loco/noid.toml
printf "slow_identifier = false\\n" > out/loco/noslow.toml
printf "slow_identifier = true\\nvoltage_noise_per_c_v = 0.0\\ncurrent_noise_c = 0.01805\\nbranch_noise_v_per_sqrt_s = 2e-4\\n" > out/loco/ekfnoise.toml
(cat out/loco/noid.toml; grep -v slow_identifier out/loco/ekfnoise.toml) > out/loco/noid_ekfnoise.toml
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
for o in both_ids noid noslow ekfnoise noid_ekfnoise; do for b in 0 0.01; do
  E="--estimator fomiukf --no-bar --settings out/loco/$o.toml --current-bias-c $b -q"
{loco_evaluations("out/loco/{cell}_${{o}}_b$b.json")}
done; done
G=""; for o in both_ids noid noslow ekfnoise noid_ekfnoise; do for b in 0 0.01; do
{loco_inputs("$o", "out/loco/{cell}_${{o}}_b$b.json")}; done; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference noslow --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_defaults.json""",
          nested_table("loco_defaults.json"), 240, ("needs:char_calce", "needs:char_a123", "needs:char_pan_hppc",
                                                     "needs:char_pan_us06")),
    Table("loco_defaults_unseen", "tuning.md", f"""\
# the settings files are loco_defaults', the profiles research.unseen_cell's (unseen_cell)
for o in both_ids noid noslow ekfnoise noid_ekfnoise; do for b in 0 0.01; do
{unseen_runs("out/loco/$o.toml", "${o}")}
done; done
G=""; for o in both_ids noid noslow ekfnoise noid_ekfnoise; do for b in 0 0.01; do
{loco_inputs("$o", "out/loco/{cell}_${{o}}_b$b.json")}
{unseen_inputs("$o", "${o}", indent="  ")}; done; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference noslow --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_defaults_unseen.json""",
          nested_table("loco_defaults_unseen.json"), 40, ("needs:loco_defaults", "needs:unseen_cell", "needs:pybamm")),
    Table("unseen_fit_options", "tuning.md", """\
# the default fit (auto) is the unseen_cell table's
python -m research.unseen_cell run --estimators fomiukf --profile-tag _nokin --refit --fit-flags=--no-kinetics
python -m research.unseen_cell run --estimators fomiukf --profile-tag _kin --refit --fit-flags=--kinetics""",
          runs_table(tuple((f"`{cell}` {label}", f"unseen_cell/{cell}{tag}_eval.json") for cell in UNSEEN_CELLS
                           for label, tag in (("`auto` (default)", ""), ("`--no-kinetics`", "_nokin"),
                                              ("`--kinetics`", "_kin"))), UNSEEN_GROUPS),
          20, ("needs:unseen_cell", "needs:pybamm")),
    Table("unseen_ocv_truth", "tuning.md", """\
python -m research.unseen_ocv_truth --json out/unseen_ocv_truth.json   # the OCV tests are unseen_cell's""",
          lambda out: tool("unseen_ocv_truth").markdown(
              [tool("unseen_ocv_truth").OcvTruthRow(**r) for r in _read(out, "unseen_ocv_truth.json")]),
          2, ("needs:unseen_cell", "needs:pybamm")),
    Table("unseen_short_charge", "tuning.md", f"""\
# the default fit is the unseen_cell table's; on the shared cells --short-charge changes nothing (the Panasonic
# test's charge rests back at full, CALCE and A123 have no two-branch OCV test), so their default runs count for both
python -m research.unseen_cell run --profile-tag _short --refit --fit-flags=--short-charge
G=""; for o in stretch short; do
{loco_inputs("$o", "out/loco/{cell}_noslow_b0.json")}; done
for c in {" ".join(UNSEEN_CELLS)}; do G="$G stretch=out/unseen_cell/${{c}}_eval.json@$c short=out/unseen_cell/${{c}}_short_eval.json@$c"; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference stretch --exclude {TUNING_EXCLUDE} $G \\
    --json out/unseen_short_charge.json""",
          lambda out: nested_table("unseen_short_charge.json")(out) + "\n\n" + "\n\n".join(
              f"{name}, mean SOC RMSE after 600 s (%):\n\n" + runs_table(
                  tuple((f"`{cell}` {label}", f"unseen_cell/{cell}{tag}_eval.json") for cell in UNSEEN_CELLS
                        for label, tag in (("stretched (default)", ""), ("`--short-charge`", "_short"))),
                  UNSEEN_GROUPS, estimator)(out)
              for name, estimator in (("`fomiukf`", "fomiukf"), ("`ecm2rc-ekf` (its own 2-RC fit)", "ecm2rc-ekf"))),
          20, ("needs:unseen_cell", "needs:loco_defaults", "needs:pybamm")),
    Table("loco_max_tau_df", "tuning.md", REAL + f"""\
mkdir -p out/loco   # the default (1000 s) is loco_defaults' noslow runs on the char_* and unseen_cell profiles
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
F="--max-tau-df 3000 -q"; o=out/loco
socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 $F -o $o/calce_tau3000.toml
socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis \\
    --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv $F -o $o/a123_tau3000.toml
socd fit $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_HPPC.csv --capacity-ah 2.77 --full-at 0 $F -o $o/pan_hppc_tau3000.toml
socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_US06.csv --capacity-ah 2.77 $F \\
    -o $o/pan_us06_tau3000.toml
for b in 0 0.01; do
  E="--estimator fomiukf --no-bar --settings out/loco/noslow.toml --current-bias-c $b -q"
{loco_evaluations("out/loco/{cell}_tau3000_b$b.json", "out/loco/{profile}_tau3000.toml")}
{unseen_runs("out/loco/noslow.toml", "tau3000", refit="--max-tau-df 3000")}
done
G=""; for b in 0 0.01; do
{loco_inputs("tau1000", "out/loco/{cell}_noslow_b$b.json", named=True)}
{unseen_inputs("tau1000", "noslow", indent="  ", named=True)}
{loco_inputs("tau3000", "out/loco/{cell}_tau3000_b$b.json", named=True)}
{unseen_inputs("tau3000", "tau3000", indent="  ", named=True)}; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference tau1000 --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_max_tau_df.json""",
          nested_table("loco_max_tau_df.json"), 150,
          ("needs:loco_defaults", "needs:loco_defaults_unseen", "needs:pybamm")),
    Table("unseen_ocv_beyond", "tuning.md", f"""\
# hold is the default: the 40 °C runs are the unseen_cell_40 table's; the shared cells have one OCV temperature
# (an OCV test or table at 25 °C), where the two rules are the same, so their default runs count for both
python -m research.unseen_cell run --ambients 40,25,10,0 --ocv-ambients 25,10,0 --profile-tag _40lin --refit \\
    --fit-flags="--ocv-beyond linear"
for v in hold linear; do
  python -m research.unseen_cell run --cells Chen2020,Mohtat2020 --ambients 25,10,0,-10 --ocv-ambients 25,10,0 \\
      --profile-tag _m10$v --refit --fit-flags="--ocv-beyond $v"
done
G=""; for o in hold linear; do
{loco_inputs("$o", "out/loco/{cell}_noslow_b0.json")}; done
for c in {" ".join(UNSEEN_CELLS)}; do G="$G hold=out/unseen_cell/${{c}}_40_eval.json@$c linear=out/unseen_cell/${{c}}_40lin_eval.json@$c"; done
for c in Chen2020 Mohtat2020; do
  G="$G hold=out/unseen_cell/${{c}}_m10hold_eval.json@$c linear=out/unseen_cell/${{c}}_m10linear_eval.json@$c"; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference hold --exclude {TUNING_EXCLUDE} $G \\
    --json out/unseen_ocv_beyond.json""",
          lambda out: nested_table("unseen_ocv_beyond.json")(out) + "\n\n`fomiukf`'s mean SOC RMSE after 600 s (%), "
          "OCV tests at 25, 10 and 0 °C only:\n\n" + runs_table(
              tuple((f"`{cell}` {v}", f"unseen_cell/{cell}{tag}_eval.json") for cell in UNSEEN_CELLS
                    for v, tag in (("hold", "_40"), ("linear", "_40lin"))) + tuple(
                  (f"`{cell}` {v}, −10 °C fit", f"unseen_cell/{cell}_m10{v}_eval.json")
                  for cell in ("Chen2020", "Mohtat2020") for v in ("hold", "linear")),
              (("40 °C", r"_40C_"),) + UNSEEN_GROUPS + (("−10 °C", r"_m10C_"),))(out),
          40, ("needs:unseen_cell_40", "needs:loco_defaults", "needs:pybamm")),
    Table("loco_current_noise", "tuning.md",
          loco_sweep("current_noise_c", "cn", ("0.0036", "0.00722", "0.0144", "0.0576"), "0.0288"),
          nested_table("loco_current_noise.json"), 50, ("needs:loco_defaults",)),
    Table("loco_voltage_noise", "tuning.md",
          loco_sweep("voltage_noise_per_c_v", "vn", ("0.0277", "0.0554", "0.111", "0.444"), "0.222"),
          nested_table("loco_voltage_noise.json"), 50, ("needs:loco_defaults",)),
    Table("loco_voltage_noise_unseen", "tuning.md",
          loco_sweep("voltage_noise_per_c_v", "vn", ("0.0554", "0.111"), "0.222", unseen=True),
          nested_table("loco_voltage_noise_unseen.json"), 50,
          ("needs:loco_defaults", "needs:loco_defaults_unseen", "needs:pybamm")),
    Table("loco_ukf_alpha_unseen", "tuning.md",
          loco_sweep("ukf_alpha", "ua", ("0.5", "0.2"), "1.0", unseen=True),
          lambda out: nested_table("loco_ukf_alpha_unseen.json")(out) + "\n\n" + "\n\n".join(
              f"{title}, mean SOC RMSE after 600 s (%):\n\n" + runs_table(
                  tuple((f"α = {a}{', +1 % offset' if b == '0.01' else ''}",
                         f"loco/{cell}_noslow_b{b}.json" if a == "1.0" else f"cn/{cell}_ua{a}_b{b}.json")
                        for b in offsets for a in ("1.0", "0.5", "0.2")), groups)(out)
              for title, cell, groups, offsets in (
                  ("CALCE", "calce", CALCE_REST_GROUPS, ("0", "0.01")),
                  ("A123", "a123", (("FUDS, US06", r"calce_a123"),), ("0", "0.01")),
                  ("Panasonic, HPPC profile", "panhppc", PAN_GROUPS, ("0",)))),
          120,
          ("needs:loco_defaults", "needs:loco_defaults_unseen", "needs:pybamm")),
    Table("loco_identifier_prior", "tuning.md",
          loco_sweep("param_init_std_rel", "ip", ("0.01", "0.03", "0.05", "0.1", "0.2"), "0.02"),
          nested_table("loco_identifier_prior.json"), 60, ("needs:loco_defaults",)),
    Table("loco_model_error_shape", "tuning.md",
          loco_sweep("voltage_noise_rel_overpotential", "ro", ("0.1", "0.25"),
                     "0.222 V per C-rate, no overpotential term", fixed="voltage_noise_per_c_v = 0.0554\\n",
                     reference="vn0.222"),
          nested_table("loco_model_error_shape.json"), 30, ("needs:loco_defaults",)),
    Table("loco_model_error_fit", "tuning.md",
          loco_sweep("voltage_noise_per_fit_rmse", "fr", ("4", "8", "12"), "0: 0.222 V per C-rate at every temperature",
                     reference="vn0.222"),
          lambda out: nested_table("loco_model_error_fit.json")(out)
          + "\n\nThe Panasonic HPPC profile per temperature, without the offset (mean SOC RMSE after 600 s, %, of "
          "`fomiukf`):\n\n" + runs_table((("default (0.222 V per C-rate)", "loco/panhppc_noslow_b0.json"),)
                                          + tuple((f"k = {k}", f"cn/panhppc_fr{k}_b0.json") for k in (4, 8, 12)),
                                          PAN_GROUPS)(out),
          30, ("needs:loco_defaults",)),
    Table("sigma_calibration", "tuning.md", REAL + """\
# the profiles are the char_* tables' (out/s25/); the 10 °C trise files are not tuned for (DESIGN §7)
S=""; for fa in DST_50soc@10015 FUDS_80soc@9999 FUDS_50soc@5080 US06_50soc@10160 US06_80soc@9984; do
  S="$S calce=out/s25/calce.toml:$C/calce20r_25C_${fa%@*}.csv@${fa#*@}"; done
S="$S a123=out/s25/a123.toml:$A/calce_a123_20C_FUDS.csv@4478 a123=out/s25/a123.toml:$A/calce_a123_20C_US06.csv@4436"
PANX="$(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v -e HPPC -e trise)"
for f in $PANX; do S="$S panasonic=out/s25/pan_hppc.toml:$f"; done
for f in $(echo $PANX | tr ' ' '\\n' | grep -v US06); do S="$S panasonic=out/s25/pan_us06.toml:$f"; done
python -m research.sigma_calibration --bias 0 --bias 0.01 --jobs 2 --json out/sigma_calibration.json $S
""", lambda out: tool("sigma_calibration").markdown(out / "sigma_calibration.json"), 15,
          ("needs:char_calce", "needs:char_a123", "needs:char_pan_hppc", "needs:char_pan_us06")),
    Table("sigma_calibration_unseen", "tuning.md", """\
# the profiles and drives are research.unseen_cell's (each cell's OCV tests and one US06 per ambient fitted)
S=""; for c in Chen2020 Mohtat2020 Marquis2019; do
  for f in $(ls out/unseen_cell/${c}_{25C,10C,0C}_*.csv | grep -v -e US06 -e HPPC -e _ocv); do
    S="$S $c=out/unseen_cell/$c.toml:$f"; done; done
python -m research.sigma_calibration --bias 0 --bias 0.01 --jobs 2 --json out/sigma_calibration_unseen.json $S
""", lambda out: tool("sigma_calibration").markdown(out / "sigma_calibration_unseen.json"), 15,
          ("needs:unseen_cell", "needs:pybamm")),
    Table("loco_ocv_error", "tuning.md",
          loco_sweep("ocv_error_std_v", "oe", ("0.01", "0.02"), "0"),
          lambda out: nested_table("loco_ocv_error.json")(out)
          + "\n\nWithout the offset (mean SOC RMSE after 600 s, %, of `fomiukf`), CALCE and the Panasonic HPPC "
          "profile:\n\n" + runs_table(
              tuple((f"{lab} CALCE", f"{d}/calce_{v}_b0.json") for lab, d, v in OCV_ERROR_RUNS),
              CALCE_REST_GROUPS)(out)
          + "\n\n" + runs_table(tuple((f"{lab} Panasonic HPPC", f"{d}/panhppc_{v}_b0.json")
                                       for lab, d, v in OCV_ERROR_RUNS), PAN_GROUPS)(out),
          60, ("needs:loco_defaults",)),
    Table("loco_noise_joint", "tuning.md", REAL + f"""\
mkdir -p out/cn   # the default (0.0288 C, 0.222 V per C-rate) is loco_defaults' noslow run
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
PAIRS="0.0072:0.0554 0.0072:0.111 0.0144:0.0554 0.0144:0.111"   # current_noise_c:voltage_noise_per_c_v
for cv in $PAIRS; do c=${{cv%:*}}; v=${{cv#*:}}
  printf "current_noise_c = $c\\nvoltage_noise_per_c_v = $v\\n" > out/cn/cv$c-$v.toml; for b in 0 0.01; do
  E="--estimator fomiukf --no-bar --settings out/cn/cv$c-$v.toml --current-bias-c $b -q"
{loco_evaluations("out/cn/{cell}_cv$c-${{v}}_b$b.json")}
done; done
G=""; for b in 0 0.01; do
{loco_inputs("default", "out/loco/{cell}_noslow_b$b.json")}
  for cv in $PAIRS; do c=${{cv%:*}}; v=${{cv#*:}}
{loco_inputs("cv$c-$v", "out/cn/{cell}_cv$c-${{v}}_b$b.json", indent="    ")}; done; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference default --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_noise_joint.json""",
          nested_table("loco_noise_joint.json"), 60, ("needs:loco_defaults",)),
    Table("loco_rest_anchor", "tuning.md", REAL + f"""\
mkdir -p out/loco   # anchored: char_calce's and char_pan_hppc's profiles; joint: char_joint_ocv's; A123 and the
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"   # OCV-test profile: loco_defaults' runs
for b in 0 0.01; do for v in anchored joint; do
  if [ $v = anchored ]; then c=calce; h=pan_hppc; else c=calce_joint; h=pan_hppc_joint; fi
  E="--estimator fomiukf --no-bar --settings out/loco/noslow.toml --current-bias-c $b -q"
  socd evaluate --cell out/s25/$c.toml {CALCE} $E --json out/loco/calce_${{v}}_b$b.json
  socd evaluate --cell out/s25/$h.toml $PANX $E --json out/loco/panhppc_${{v}}_b$b.json
done; done
G=""; for b in 0 0.01; do for v in anchored joint; do
  G="$G $v=out/loco/calce_${{v}}_b$b.json@calce $v=out/loco/a123_noslow_b$b.json@a123"
  G="$G $v=out/loco/panhppc_${{v}}_b$b.json@panasonic $v=out/loco/panus06_noslow_b$b.json@panasonic"; done; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference anchored --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_rest_anchor.json""",
          nested_table("loco_rest_anchor.json"), 30,
          ("needs:loco_defaults", "needs:char_calce", "needs:char_pan_hppc", "needs:char_joint_ocv")),
    Table("loco_ekf_current_noise", "tuning.md",
          loco_ekf_sweep("current_noise_c", "ekf", ("0.00225", "0.0045", "0.009", "0.01805", "0.036", "0.072"), "0.009",
                         "loco_ekf_current_noise"),
          nested_table("loco_ekf_current_noise.json"), 40, ("needs:char_calce", "needs:char_a123")),
    Table("loco_ekf_ocv_slope", "tuning.md",
          loco_ekf_sweep("ocv_slope_span_soc", "ekfslope", ("0", "0.005", "0.01", "0.02"), "0", "loco_ekf_ocv_slope"),
          lambda out: nested_table("loco_ekf_ocv_slope.json")(out)
          + "\n\nThe EKF on CALCE without the offset (mean SOC RMSE after 600 s, %):\n\n" + runs_table(
              tuple((f"span {c}", f"cn/calce_ekfslope{c}_b0.json") for c in ("0", "0.005", "0.01", "0.02")),
              CALCE_REST_GROUPS, estimator="ecm2rc-ekf")(out)
          + "\n\n" + ocv_flat_table(
              (("CALCE", "s25/calce.toml"), ("A123", "s25/a123.toml"), ("Panasonic, HPPC alone", "s25/pan_hppc.toml"),
               ("Panasonic, OCV test + US06", "s25/pan_us06.toml")))(out), 30, ("needs:char_calce", "needs:char_a123", "needs:char_pan_hppc",
                                                         "needs:char_pan_us06")),
    Table("loco_fit_options", "tuning.md", REAL + f"""\
mkdir -p out/fitopt
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
fit_and_score() {{  # VARIANT SEED FIT-FLAGS...: the four characterisations of the char_* tables, each scored
  v=$1; s=$2; shift 2; o=out/fitopt; E="--estimator fomiukf -q"
  if [ $s = 0 ]; then
    socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 "$@" -q -o $o/calce_$v.toml
    socd evaluate --cell $o/calce_$v.toml {CALCE} $E --json $o/calce_$v.json
    socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_US06.csv --capacity-ah 2.77 "$@" -q -o $o/panus06_$v.toml
    socd evaluate --cell $o/panus06_$v.toml $(echo $PANX | tr ' ' '\\n' | grep -v US06) $E --json $o/panus06_$v.json
  fi
  socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis \\
      --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv "$@" --seed $s --candidates 1 -q -o $o/a123s${{s}}_$v.toml
  socd evaluate --cell $o/a123s${{s}}_$v.toml {A123} $E --json $o/a123s${{s}}_$v.json
  if [ $s != 2 ]; then
    socd fit $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_HPPC.csv --capacity-ah 2.77 --full-at 0 "$@" --seed $s --candidates 1 -q -o $o/panhppcs${{s}}_$v.toml
    socd evaluate --cell $o/panhppcs${{s}}_$v.toml $PANX $E --json $o/panhppcs${{s}}_$v.json
  fi
}}
fit_and_score auto 0; fit_and_score nokin 0 --no-kinetics; fit_and_score kin 0 --kinetics
fit_and_score nokin_mo5 0 --no-kinetics --min-order 0.5; fit_and_score auto_ms150 0 --max-seconds 150
for s in 1 2; do fit_and_score nokin $s --no-kinetics; fit_and_score kin $s --kinetics; done
G=""; for v in auto nokin kin nokin_mo5 auto_ms150; do
  G="$G $v=out/fitopt/calce_$v.json@calce $v=out/fitopt/a123s0_$v.json@a123"
  G="$G $v=out/fitopt/panhppcs0_$v.json@panasonic $v=out/fitopt/panus06_$v.json@panasonic"; done
python -m research.nested_tuning --by cell --estimator fomiukf $G --json out/loco_fit_options.json""",
          lambda out: nested_table("loco_fit_options.json")(out) + "\n\nThe same fits with other optimiser seeds "
          "(`--seed`; mean SOC RMSE after 600 s, %, of `fomiukf`):\n\n" + runs_table(
              tuple((f"{cell} `{v}` seed {s}", f"fitopt/{cell}s{s}_{v}.json") for cell, seeds in
                    (("a123", (0, 1, 2)), ("panhppc", (0, 1))) for v in ("nokin", "kin") for s in seeds),
              (("A123 (all)", r"calce_a123"),) + PAN_GROUPS)(out),
          150),
    Table("char_calce", "characterisation.md", REAL + f"""\
socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 -q -o out/s25/calce.toml
socd evaluate --cell out/s25/calce.toml {CALCE} --estimator fomiukf -q --json out/s25/calce_def.json""",
          evaluate_table("s25/calce_def.json"), 8),
    Table("char_a123", "characterisation.md", REAL + f"""\
socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis \\
    --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv -q -o out/s25/a123.toml
socd evaluate --cell out/s25/a123.toml {A123} --estimator fomiukf -q --json out/s25/a123_eval.json""",
          evaluate_table("s25/a123_eval.json"), 6),
    Table("char_pan_hppc", "characterisation.md", REAL + """\
socd fit $P/pan18650pf_{25C,10C,0C,m10C,m20C}_HPPC.csv --capacity-ah 2.77 --full-at 0 -q -o out/s25/pan_hppc.toml
socd evaluate --cell out/s25/pan_hppc.toml $(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v HPPC) \\
    --estimator fomiukf -q --json out/s25/pan_hppc_eval.json""",
          group_table("s25/pan_hppc_eval.json", PAN_GROUPS), 60),
    Table("hppc_pulse_check", "characterisation.md", REAL + """\
python -m research.pulse_fit_check out/s25/pan_hppc.toml $P/pan18650pf_{25C,10C,0C,m10C,m20C}_HPPC.csv \\
    --capacity-ah 2.77 --json out/s25/hppc_pulse_check.json   # out/s25/pan_hppc.toml: char_pan_hppc""",
          lambda out: tool("pulse_fit_check").table(tool("pulse_fit_check").read_json(str(out / "s25/hppc_pulse_check.json"))),
          2, ("needs:char_pan_hppc",)),
    Table("hppc_ocv_between_rests", "cell_options.md", REAL + """\
PANX="$(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v HPPC)"   # near-reference (the default): char_pan_hppc's
for v in joint settled interpolate; do
  socd fit $P/pan18650pf_{25C,10C,0C,m10C,m20C}_HPPC.csv --capacity-ah 2.77 --full-at 0 --ocv-between-rests $v -q \\
      -o out/s25/pan_hppc_between_$v.toml
  socd evaluate --cell out/s25/pan_hppc_between_$v.toml $PANX --estimator fomiukf -q \\
      --json out/s25/pan_hppc_between_${v}_eval.json
done""",
          lambda out: runs_table((("`near-reference` (default)", "s25/pan_hppc_eval.json"),
                                  ("`joint`", "s25/pan_hppc_between_joint_eval.json"),
                                  ("`settled`", "s25/pan_hppc_between_settled_eval.json"),
                                  ("`interpolate`", "s25/pan_hppc_between_interpolate_eval.json")), PAN_GROUPS)(out)
          + "\n\nThe 2-RC EKF on its own fit (the same in every run: the option does not touch it):\n\n"
          + runs_table((("`ecm2rc-ekf`", "s25/pan_hppc_eval.json"),), PAN_GROUPS, "ecm2rc-ekf")(out),
          25, ("needs:char_pan_hppc",)),
    Table("unseen_cell_hppc", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2
python -m research.unseen_cell run --fit-drive HPPC --profile-tag _hppc --refit &
python -m research.unseen_cell run --fit-drive HPPC --profile-tag _hppc_noanchor --fit-flags=--no-rest-anchor --refit
wait
python -m research.unseen_cell run --fit-drive HPPC --profile-tag _hppc_joint --fit-flags="--ocv-between-rests joint" --refit &
python -m research.unseen_cell run --fit-drive HPPC --profile-tag _hppc_settled --fit-flags="--ocv-between-rests settled" --refit
wait""",
          lambda out: "\n\n".join(
              f"`{c}`:\n\n" + runs_table((("rest anchor, `near-reference` (default)", f"unseen_cell/{c}_hppc_eval.json"),
                                           ("`--no-rest-anchor`", f"unseen_cell/{c}_hppc_noanchor_eval.json"),
                                           ("`--ocv-between-rests joint`", f"unseen_cell/{c}_hppc_joint_eval.json"),
                                           ("`--ocv-between-rests settled`", f"unseen_cell/{c}_hppc_settled_eval.json"),
                                           ("2-RC EKF, its own fit", f"unseen_cell/{c}_hppc_eval.json", "ecm2rc-ekf")),
                                          UNSEEN_GROUPS)(out)
              for c in UNSEEN_CELLS), 40),
    Table("loco_ocv_between_rests", "characterisation.md", """\
G=""; for v in joint settled; do
  G="$G $v=out/s25/pan_hppc_between_${v}_eval.json@panasonic"
  for c in Chen2020 Mohtat2020 Marquis2019; do G="$G $v=out/unseen_cell/${c}_hppc_${v}_eval.json@$c"; done
done
G="$G near-reference=out/s25/pan_hppc_eval.json@panasonic"
for c in Chen2020 Mohtat2020 Marquis2019; do G="$G near-reference=out/unseen_cell/${c}_hppc_eval.json@$c"; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference near-reference --exclude _10C_trise $G \\
    --json out/loco_ocv_between_rests.json""",
          nested_table("loco_ocv_between_rests.json"), 1,
          ("needs:char_pan_hppc", "needs:hppc_ocv_between_rests", "needs:unseen_cell_hppc")),
    Table("loco_reference_shape", "characterisation.md", REAL + """\
python -m research.unseen_cell build --jobs 2
python -m research.unseen_cell run --fit-drive HPPC --profile-tag _hppc --refit &
python -m research.unseen_cell run --fit-drive HPPC --profile-tag _hppc_refshape \\
    --fit-flags="--ocv-between-rests reference-shape" --refit &
PANX="$(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v HPPC)"   # near-reference (the default): char_pan_hppc's
socd fit $P/pan18650pf_{25C,10C,0C,m10C,m20C}_HPPC.csv --capacity-ah 2.77 --full-at 0 --ocv-between-rests reference-shape \\
    -q -o out/s25/pan_hppc_between_reference-shape.toml
socd evaluate --cell out/s25/pan_hppc_between_reference-shape.toml $PANX --estimator fomiukf -q \\
    --json out/s25/pan_hppc_between_reference-shape_eval.json
wait
G="reference-shape=out/s25/pan_hppc_between_reference-shape_eval.json@panasonic"
G="$G near-reference=out/s25/pan_hppc_eval.json@panasonic"
for c in Chen2020 Mohtat2020 Marquis2019; do
  G="$G reference-shape=out/unseen_cell/${c}_hppc_refshape_eval.json@$c near-reference=out/unseen_cell/${c}_hppc_eval.json@$c"
done
python -m research.nested_tuning --by cell --estimator fomiukf --reference near-reference --exclude _10C_trise $G \\
    --json out/loco_reference_shape.json""",
          lambda out: nested_table("loco_reference_shape.json")(out) + "\n\n" + runs_table(
              (("Panasonic, `near-reference` (default)", "s25/pan_hppc_eval.json"),
               ("Panasonic, `reference-shape`", "s25/pan_hppc_between_reference-shape_eval.json")), PAN_GROUPS)(out)
          + "\n\n" + runs_table(tuple((f"`{c}`, {label}", f"unseen_cell/{c}{tag}_eval.json") for c in UNSEEN_CELLS
                                        for label, tag in (("`near-reference` (default)", "_hppc"),
                                                           ("`reference-shape`", "_hppc_refshape"))), UNSEEN_GROUPS)(out),
          45, ("needs:char_pan_hppc", "needs:pybamm")),
    Table("loco_pure_ohmic", "characterisation.md", REAL + """\
python -m research.unseen_cell build --jobs 2
python -m research.unseen_cell build --jobs 2 --cells Chen2020,Mohtat2020 --ambients -10
for f in 0 0.25; do
  python -m research.unseen_cell run --fit-drive HPPC --cells Chen2020,Mohtat2020 --ambients 25,10,0,-10 \\
      --profile-tag _hppc_pure$f --fit-flags="--pure-ohmic-share $f" --refit &
  python -m research.unseen_cell run --fit-drive HPPC --cells Marquis2019 --profile-tag _hppc_pure$f \\
      --fit-flags="--pure-ohmic-share $f" --refit &
  socd fit $P/pan18650pf_{25C,10C,0C,m10C,m20C}_HPPC.csv --capacity-ah 2.77 --full-at 0 --pure-ohmic-share $f -q \\
      -o out/s25/pan_hppc_pure$f.toml
  socd evaluate --cell out/s25/pan_hppc_pure$f.toml $(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v HPPC) \\
      --estimator fomiukf -q --json out/s25/pan_hppc_pure${f}_eval.json
  wait
done
G=""; for f in 0 0.25; do
  G="$G $f=out/s25/pan_hppc_pure${f}_eval.json@panasonic"
  for c in Chen2020 Mohtat2020 Marquis2019; do G="$G $f=out/unseen_cell/${c}_hppc_pure${f}_eval.json@$c"; done
done
python -m research.nested_tuning --by cell --estimator fomiukf --reference 0 --exclude _10C_trise $G \\
    --json out/loco_pure_ohmic.json""",
          lambda out: nested_table("loco_pure_ohmic.json")(out) + "\n\n" + runs_table(
              tuple((f"Panasonic, `--pure-ohmic-share {f}`", f"s25/pan_hppc_pure{f}_eval.json") for f in ("0", "0.25")),
              PAN_GROUPS)(out)
          + "\n\n" + runs_table(tuple((f"`{c}`, `--pure-ohmic-share {f}`", f"unseen_cell/{c}_hppc_pure{f}_eval.json")
                                        for c in UNSEEN_CELLS for f in ("0", "0.25"))
                                  + tuple((f"`{c}`, 2-RC EKF, its own fit", f"unseen_cell/{c}_hppc_pure0_eval.json",
                                           "ecm2rc-ekf") for c in UNSEEN_CELLS), UNSEEN_M10_GROUPS)(out),
          90, ("needs:pybamm",)),
    Table("hppc_i0_bound", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2
python -m research.unseen_cell build --jobs 2 --cells Chen2020,Mohtat2020 --ambients -10
# where the default's fit reached the bound (on Chen2020 and Mohtat2020: nowhere); the rest of each log is dropped
for c in Chen2020 Mohtat2020; do
  python -m research.unseen_cell fit --fit-drive HPPC --cells $c --ambients 25,10,0,-10 --profile-tag _hppc_c1 \\
      --fit-flags="--candidates 1" --refit 2>&1 | grep "search's lower bound" || echo "$c: no i0 at its lower bound"
done
# the default (refit linear at the bound) against --kinetics (i0 kept at the bound) where it fired
python -m research.unseen_cell run --fit-drive HPPC --cells Marquis2019 --profile-tag _hppc_c1 \\
    --fit-flags="--candidates 1" --refit
python -m research.unseen_cell run --fit-drive HPPC --cells Marquis2019 --profile-tag _hppc_kin1 \\
    --fit-flags="--kinetics --candidates 1" --refit""",
          runs_table((("`Marquis2019`, default (refit linear at the bound)", "unseen_cell/Marquis2019_hppc_c1_eval.json"),
                      ("`Marquis2019`, `--kinetics` (kept at the bound)", "unseen_cell/Marquis2019_hppc_kin1_eval.json"),
                      ("`Marquis2019`, 2-RC EKF, its own fit", "unseen_cell/Marquis2019_hppc_c1_eval.json",
                       "ecm2rc-ekf")), UNSEEN_GROUPS),
          40, ("needs:pybamm",)),
    Table("filter_on_two_rc_model", "characterisation.md", REAL + f"""\
# the Panasonic profile is loco_pure_ohmic's default one (--pure-ohmic-share 0), scored there
python -m research.two_rc_point out/s25/pan_hppc_pure0.toml out/s25/pan_hppc_2rc_whole.toml --ocv two-rc
socd evaluate --cell out/s25/pan_hppc_2rc_whole.toml $(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC) \\
    --estimator fomiukf --no-bar -q --json out/s25/pan_hppc_2rc_whole_eval.json
socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 -q -o out/s25/calce_f2.toml
python -m research.two_rc_point out/s25/calce_f2.toml out/s25/calce_2rc_whole.toml --ocv two-rc
socd evaluate --cell out/s25/calce_f2.toml {CALCE} --estimator fomiukf -q --json out/s25/calce_f2_eval.json
socd evaluate --cell out/s25/calce_2rc_whole.toml {CALCE} --estimator fomiukf --no-bar -q \\
    --json out/s25/calce_2rc_whole_eval.json
# A123 with char_a123's command (its OCV table on the charge branch, --hysteresis)
socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis \\
    --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv -q -o out/s25/a123_f2.toml
python -m research.two_rc_point out/s25/a123_f2.toml out/s25/a123_2rc_whole.toml --ocv two-rc
socd evaluate --cell out/s25/a123_f2.toml {A123} --estimator fomiukf -q --json out/s25/a123_f2_eval.json
socd evaluate --cell out/s25/a123_2rc_whole.toml {A123} --estimator fomiukf --no-bar -q --json out/s25/a123_2rc_whole_eval.json""",
          lambda out: "\n\n".join(
              runs_table((("`fomiukf`, the fitted profile", f"s25/{fitted}_eval.json"),
                          ("`fomiukf`, the EKF's own model", f"s25/{whole}_eval.json"),
                          ("`ecm2rc-ekf`, its own model", f"s25/{fitted}_eval.json", "ecm2rc-ekf")), groups)(out)
              for fitted, whole, groups in (("pan_hppc_pure0", "pan_hppc_2rc_whole", PAN_GROUPS),
                                            ("calce_f2", "calce_2rc_whole", CALCE_ALL),
                                            ("a123_f2", "a123_2rc_whole", A123_ALL))),
          15, ("needs:loco_pure_ohmic",)),
    Table("loco_flat_ocv", "tuning.md", REAL + f"""\
mkdir -p out/fo
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
# the profiles: filter_on_two_rc_model's CALCE and A123 ones, loco_pure_ohmic's HPPC-alone ones (default flags)
{sweep_head("flat_run", "flat_ocv_noise_v", "fo", "fo")}  U="--fit-drive HPPC --profile-tag _hppc_pure0 --estimators fomiukf --settings out/fo/fo$1.toml --current-bias-c $2"
  python -m research.unseen_cell run $U --cells Chen2020,Mohtat2020 --ambients 25,10,0,-10 --tag _fo$1_b$2
  python -m research.unseen_cell run $U --cells Marquis2019 --tag _fo$1_b$2
}}
flat_run 0 0 & flat_run 0.02 0 & wait
flat_run 0.1 0 & flat_run 0 0.01 & wait
flat_run 0.02 0.01 & flat_run 0.1 0.01 & wait
G=""; for v in 0 0.02 0.1; do for b in 0 0.01; do
  G="$G $v=out/fo/calce_fo${{v}}_b$b.json@calce $v=out/fo/a123_fo${{v}}_b$b.json@a123 $v=out/fo/pan_fo${{v}}_b$b.json@panasonic"
  for c in {" ".join(UNSEEN_CELLS)}; do G="$G $v=out/unseen_cell/${{c}}_hppc_pure0_fo${{v}}_b${{b}}_eval.json@$c"; done
done; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference 0 --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_flat_ocv.json""",
          lambda out: nested_table("loco_flat_ocv.json")(out) + "\n\n" + runs_table(
              tuple((f"CALCE, {v} V" + (", +1 % offset" if b == "0.01" else ""), f"fo/calce_fo{v}_b{b}.json")
                    for b in ("0", "0.01") for v in ("0", "0.02", "0.1")), CALCE_REST_GROUPS)(out)
          + "\n\n" + runs_table(tuple((f"Panasonic, HPPC alone, {v} V", f"fo/pan_fo{v}_b0.json")
                                        for v in ("0", "0.02", "0.1")), PAN_GROUPS)(out)
          + "\n\n" + runs_table(tuple((f"`{c}`, {v} V", f"unseen_cell/{c}_hppc_pure0_fo{v}_b0_eval.json")
                                        for c in UNSEEN_CELLS for v in ("0", "0.02", "0.1")), UNSEEN_M10_GROUPS)(out),
          80, ("needs:pybamm", "needs:loco_pure_ohmic", "needs:filter_on_two_rc_model")),
    Table("loco_branch_walk", "tuning.md", REAL + f"""\
mkdir -p out/bw
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
# loco_flat_ocv's profiles, and unseen_cell_more's three cells (OCV test + one US06 per temperature)
{sweep_head("walk_run", "branch_noise_v_per_sqrt_s", "bw", "bw")}  U="--estimators fomiukf --settings out/bw/bw$1.toml --current-bias-c $2 --tag _bw$1_b$2"
  python -m research.unseen_cell run $U --fit-drive HPPC --profile-tag _hppc_pure0 --cells Chen2020,Mohtat2020 --ambients 25,10,0,-10
  python -m research.unseen_cell run $U --fit-drive HPPC --profile-tag _hppc_pure0 --cells Marquis2019
  python -m research.unseen_cell run $U --cells {",".join(MORE_UNSEEN_CELLS)} --ambients 25,10 --workdir out/unseen_more
}}
walk_run 1e-4 0 & walk_run 3e-4 0 & wait
walk_run 1e-3 0 & walk_run 1e-4 0.01 & wait
walk_run 3e-4 0.01 & walk_run 1e-3 0.01 & wait
G=""; for v in 1e-4 3e-4 1e-3; do for b in 0 0.01; do
  G="$G $v=out/bw/calce_bw${{v}}_b$b.json@calce $v=out/bw/a123_bw${{v}}_b$b.json@a123 $v=out/bw/pan_bw${{v}}_b$b.json@panasonic"
  for c in {" ".join(UNSEEN_CELLS)}; do G="$G $v=out/unseen_cell/${{c}}_hppc_pure0_bw${{v}}_b${{b}}_eval.json@$c"; done
  for c in {" ".join(MORE_UNSEEN_CELLS)}; do G="$G $v=out/unseen_more/${{c}}_bw${{v}}_b${{b}}_eval.json@$c"; done
done; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference 1e-4 --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_branch_walk.json""",
          lambda out: nested_table("loco_branch_walk.json")(out)
          + "\n\n" + runs_table(tuple((f"Panasonic, HPPC alone, {v} V/√s", f"bw/pan_bw{v}_b0.json")
                                        for v in ("1e-4", "3e-4", "1e-3")), PAN_GROUPS)(out)
          + "\n\n" + runs_table(tuple((f"`{c}`, {v} V/√s", f"unseen_more/{c}_bw{v}_b0_eval.json")
                                        for c in MORE_UNSEEN_CELLS for v in ("1e-4", "3e-4", "1e-3")),
                                  UNSEEN_GROUPS[:2])(out),
          70, ("needs:pybamm", "needs:loco_pure_ohmic", "needs:filter_on_two_rc_model", "needs:unseen_cell_more")),
    Table("loco_correlation_cap", "tuning.md", REAL + f"""\
mkdir -p out/vif   # the profiles are the char_* tables' (out/s25/): socd fit's defaults
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
cap_run() {{  # CAP BIAS: both filters with adaptive_noise_correlation_cap = CAP, current offset BIAS x 1C
  printf "adaptive_noise_correlation_cap = $1\\n[ecm2rc_ekf]\\nadaptive_noise_correlation_cap = $1\\n" > out/vif/cap$1.toml
  E="--estimator fomiukf --estimator ecm2rc-ekf --no-bar --settings out/vif/cap$1.toml --current-bias-c $2 -q"
  socd evaluate --cell out/s25/calce.toml {CALCE} $E --json out/vif/calce_cap$1_b$2.json
  socd evaluate --cell out/s25/a123.toml {A123} $E --json out/vif/a123_cap$1_b$2.json
  socd evaluate --cell out/s25/pan_hppc.toml $PANX $E --json out/vif/pan_cap$1_b$2.json
}}
cap_run 1 0 & cap_run 10 0 & wait
cap_run 30 0 & cap_run 1 0.01 & wait
cap_run 10 0.01 & cap_run 30 0.01 & wait
G=""; for v in 1 10 30; do for b in 0 0.01; do
  G="$G $v=out/vif/calce_cap${{v}}_b$b.json@calce $v=out/vif/a123_cap${{v}}_b$b.json@a123 $v=out/vif/pan_cap${{v}}_b$b.json@panasonic"
done; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference 1 --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_correlation_cap.json
python -m research.nested_tuning --by cell --estimator ecm2rc-ekf --reference 1 --exclude {TUNING_EXCLUDE} $G \\
    --json out/loco_correlation_cap_ekf.json""",
          lambda out: nested_table("loco_correlation_cap.json")(out)
          + "\n\nThe 2-RC EKF, tuned the same way:\n\n" + nested_table("loco_correlation_cap_ekf.json")(out)
          + "\n\n" + runs_table(tuple((f"Panasonic, HPPC alone, cap {v}" + (", +1 % offset" if b == "0.01" else ""),
                                          f"vif/pan_cap{v}_b{b}.json", e)
                                         for e in ("fomiukf", "ecm2rc-ekf") for b in ("0", "0.01")
                                         for v in ("1", "10", "30")), PAN_GROUPS)(out),
          120, ("needs:char_calce", "needs:char_a123", "needs:char_pan_hppc")),
    Table("char_joint_ocv", "characterisation.md", REAL + f"""\
socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 --no-rest-anchor -q -o out/s25/calce_joint.toml
socd evaluate --cell out/s25/calce_joint.toml {CALCE} --estimator fomiukf -q --json out/s25/calce_joint_eval.json
socd fit $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_HPPC.csv --capacity-ah 2.77 --full-at 0 --no-rest-anchor -q \\
    -o out/s25/pan_hppc_joint.toml
socd evaluate --cell out/s25/pan_hppc_joint.toml $(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC) \\
    --estimator fomiukf -q --json out/s25/pan_hppc_joint_eval.json""",
          lambda out: evaluate_table("s25/calce_joint_eval.json")(out) + "\n\n"
          + group_table("s25/pan_hppc_joint_eval.json", PAN_GROUPS)(out), 20),
    Table("char_pan_us06", "characterisation.md", REAL + """\
socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{25C,10C,0C,m10C,m20C}_US06.csv --capacity-ah 2.77 -q \\
    -o out/s25/pan_us06.toml
socd evaluate --cell out/s25/pan_us06.toml $(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v -e HPPC -e US06) \\
    --estimator fomiukf -q --json out/s25/pan_us06_eval.json""",
          group_table("s25/pan_us06_eval.json", PAN_GROUPS), 60),
    Table("sample_period", "characterisation.md", REAL + """\
H=$P/fullrate_10Hz; mkdir -p out/hz10
socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{25C,10C,0C,m10C,m20C}_US06.csv --capacity-ah 2.77 -q \\
    -o out/hz10/pan_us06_1s.toml
# the 10 Hz logs as socd fit reads them by default (block-averaged to 1 s) and at their own rate
socd fit $D/ocv/ocv_pan18650pf_25C.csv $H/pan18650pf_{25C,10C,0C,m10C,m20C}_US06_10Hz.csv --capacity-ah 2.77 -q \\
    -o out/hz10/pan_us06_10hzavg.toml
socd fit $D/ocv/ocv_pan18650pf_25C.csv $H/pan18650pf_{25C,10C,0C,m10C,m20C}_US06_10Hz.csv --capacity-ah 2.77 -q \\
    --fit-period 0 -o out/hz10/pan_us06_10hz.toml
printf "memory_follows_sample_period = false\\n" > out/hz10/samples.toml   # L = 16 samples at any period
for v in 1s 10hzavg 10hz; do
  socd evaluate --cell out/hz10/pan_us06_$v.toml $H/pan18650pf_25C_LA92_10Hz.csv \\
      $(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v -e HPPC -e US06) --estimator fomiukf -q \\
      --json out/hz10/${v}_span.json
  socd evaluate --cell out/hz10/pan_us06_$v.toml $H/pan18650pf_25C_LA92_10Hz.csv \\
      $(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v -e HPPC -e US06) --estimator fomiukf -q --no-bar \\
      --settings out/hz10/samples.toml --json out/hz10/${v}_samples.json
done""",
          lambda out: runs_table(
              tuple((f"{fit}, memory {rule}", f"hz10/{tag}_{m}.json")
                    for fit, tag in (("fitted on the 1 s files", "1s"),
                                     ("fitted on the 10 Hz logs, averaged to 1 s (default)", "10hzavg"),
                                     ("fitted on the 10 Hz logs at 10 Hz (`--fit-period 0`)", "10hz"))
                    for rule, m in (("as a span (default)", "span"), ("as 16 samples", "samples"))),
              SAMPLE_PERIOD_GROUPS)(out) + "\n\nThe 2-RC EKF on each profile's own 2-RC fit (no G-L memory):\n\n"
          + runs_table((("fitted on the 1 s files", "hz10/1s_span.json"),
                        ("fitted on the 10 Hz logs, averaged to 1 s (default)", "hz10/10hzavg_span.json"),
                        ("fitted on the 10 Hz logs at 10 Hz (`--fit-period 0`)", "hz10/10hz_span.json")),
                       SAMPLE_PERIOD_GROUPS, "ecm2rc-ekf")(out), 45),
    Table("unseen_cell", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2
python -m research.unseen_cell run --refit""", unseen_table("unseen_cell"), 15, ("needs:pybamm",)),
    Table("unseen_cell_more", "characterisation.md", """\
W=out/unseen_more
python -m research.unseen_cell build --cells Ai2020,OKane2022,Ecker2015 --ambients 25,10 --jobs 2 --workdir $W
python -m research.unseen_cell run --cells Ai2020,OKane2022,Ecker2015 --ambients 25,10 --workdir $W --refit""",
          unseen_table("unseen_more", MORE_UNSEEN_CELLS, groups=UNSEEN_GROUPS[:2]), 30, ("needs:pybamm",)),
    Table("unseen_more_hppc", "characterisation.md", """\
W=out/unseen_more
python -m research.unseen_cell build --cells Ai2020,OKane2022,Ecker2015 --ambients 25,10,0 --jobs 2 --workdir $W
R="run --ambients 25,10,0 --workdir $W --fit-drive HPPC --profile-tag _hppc --refit"
python -m research.unseen_cell $R --cells Ai2020,Ecker2015 & python -m research.unseen_cell $R --cells OKane2022; wait""",
          unseen_table("unseen_more", MORE_UNSEEN_CELLS, tag="_hppc"), 30, ("needs:pybamm",)),
    Table("unseen_blind", "characterisation.md", """\
W=out/blind
python -m research.unseen_cell build --cells NCA_Kim2011 --ambients 25,10,0 --jobs 2 --workdir $W
python -m research.unseen_cell build --cells Ramadass2004 --ambients 40,25 --jobs 2 --workdir $W
python -m research.unseen_cell run --cells NCA_Kim2011 --ambients 25,10,0 --workdir $W --refit &
python -m research.unseen_cell run --cells Ramadass2004 --ambients 40,25 --workdir $W --refit; wait""",
          unseen_table("blind", BLIND_CELLS, groups=BLIND_GROUPS), 20, ("needs:pybamm",)),
    Table("unseen_lgm50", "characterisation.md", """\
W=out/unseen_lgm50
python -m research.unseen_cell build --cells ORegan2022,Chen2020_composite --ambients 25 --jobs 2 --workdir $W
python -m research.unseen_cell run --cells ORegan2022,Chen2020_composite --ambients 25 --workdir $W --refit""",
          unseen_table("unseen_lgm50", ("ORegan2022", "Chen2020_composite"), groups=UNSEEN_GROUPS[:1]), 15,
          ("needs:pybamm",)),
    Table("unseen_blind_hppc", "characterisation.md", """\
W=out/blind   # the recordings are unseen_blind's
R="--workdir $W --fit-drive HPPC --profile-tag _hppc --refit"
python -m research.unseen_cell run --cells NCA_Kim2011 --ambients 25,10,0 $R &
python -m research.unseen_cell run --cells Ramadass2004 --ambients 40,25 $R; wait""",
          unseen_table("blind", BLIND_CELLS, tag="_hppc", groups=BLIND_GROUPS), 20, ("needs:unseen_blind", "needs:pybamm")),
    Table("unseen_ocv_truth_more", "characterisation.md", f"""\
python -m research.unseen_ocv_truth --cells {",".join(MORE_UNSEEN_CELLS)} --ambients 25,10 --workdir out/unseen_more \\
    --json out/unseen_ocv_truth_more.json   # the OCV tests are unseen_cell_more's""",
          lambda out: tool("unseen_ocv_truth").markdown(
              [tool("unseen_ocv_truth").OcvTruthRow(**r) for r in _read(out, "unseen_ocv_truth_more.json")]),
          2, ("needs:unseen_cell_more", "needs:pybamm")),
    Table("hppc_seed_spread", "characterisation.md", REAL + SEED_FIT + """\
for s in 0 1 2 3 4 5; do seed_fit pan_s$s $s --shape each; done
for s in 0 2; do seed_fit pank4_s$s $s --starts 4 --shape each; done""",
          seed_spread_table(tuple((f"seed {s}", f"seeds/pan_s{s}") for s in range(6))
                            + tuple((f"`--starts 4` from seed {s} (seeds {s}-{s + 3})", f"seeds/pank4_s{s}") for s in (0, 2)),
                            SEED_TEMPS, SEED_GROUPS, averaged=6),
          70),
    Table("hppc_seed_spread_monotone", "characterisation.md", REAL + SEED_FIT + """\
for s in 0 1 2 3 4 5; do seed_fit mono_s$s $s --monotone --shape each; done""",
          seed_spread_table(tuple((f"seed {s}, `--monotone`", f"seeds/mono_s{s}") for s in range(6)),
                            SEED_TEMPS, SEED_GROUPS, averaged=6),
          25),
    Table("unseen_shape", "characterisation.md", """\
python -m research.unseen_cell run --profile-tag _s0_each --refit --fit-flags='--candidates 1 --shape each'
python -m research.unseen_cell run --cells Ai2020,OKane2022,Ecker2015 --ambients 25,10 --workdir out/unseen_more \\
    --profile-tag _s0_each --refit --fit-flags='--candidates 1 --shape each'
python -m research.unseen_cell run --estimators fomiukf --profile-tag _orders --refit --fit-flags='--candidates 1 --shape orders'
python -m research.unseen_cell run --cells Ai2020,OKane2022,Ecker2015 --ambients 25,10 --workdir out/unseen_more \\
    --estimators fomiukf --profile-tag _orders --refit --fit-flags='--candidates 1 --shape orders'""",
          runs_table(tuple((f"`{cell}` {label}", f"{folder}/{cell}{tag}_eval.json")
                           for folder, cells in (("unseen_cell", UNSEEN_CELLS), ("unseen_more", MORE_UNSEEN_CELLS))
                           for cell in cells
                           for label, tag in (("`--shape each`", "_s0_each"), ("`--shape orders` (the default)", "_orders"))),
                     UNSEEN_GROUPS),
          60, ("needs:unseen_cell", "needs:unseen_cell_more", "needs:pybamm")),
    Table("pan_us06_shape", "characterisation.md", REAL + """\
mkdir -p out/shape_seeds; O=out/shape_seeds   # one candidate profile at seed 0, as shape_seeds' seed 1
for sh in each orders; do
  socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{25C,10C,0C,m10C,m20C}_US06.csv --capacity-ah 2.77 -q --seed 0 --candidates 1 \\
      --shape $sh -o $O/pan_us06_s0_$sh.toml
  socd evaluate --cell $O/pan_us06_s0_$sh.toml $(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v -e HPPC -e US06) \\
      --estimator fomiukf --no-bar -q --json $O/pan_us06_s0_$sh.json
done""",
          runs_table((("`--shape each`", "shape_seeds/pan_us06_s0_each.json"),
                      ("`--shape orders` (the default)", "shape_seeds/pan_us06_s0_orders.json")), PAN_GROUPS),
          30),
    Table("hppc_seed_spread_shape", "characterisation.md", REAL + SEED_FIT + """\
for s in 0 1 2; do seed_fit panord_s$s $s --shape orders; done""",
          seed_spread_table(tuple((f"seed {s}, `--shape orders` (the default)", f"seeds/panord_s{s}") for s in range(3)),
                            SEED_TEMPS, SEED_GROUPS, averaged=3),
          35),
    Table("shape_seeds", "characterisation.md", REAL + """\
# seed 0: the unseen_shape, pan_us06_shape, hppc_seed_spread and hppc_seed_spread_shape tables' runs; every fit one candidate
mkdir -p out/shape_seeds; O=out/shape_seeds
for sh in each orders; do
  python -m research.unseen_cell run --estimators fomiukf --profile-tag _s1_$sh --refit --fit-flags="--seed 1 --candidates 1 --shape $sh"
  python -m research.unseen_cell run --cells Ai2020,OKane2022,Ecker2015 --ambients 25,10 --workdir out/unseen_more \\
      --estimators fomiukf --profile-tag _s1_$sh --refit --fit-flags="--seed 1 --candidates 1 --shape $sh"
done
for sh in each orders; do   # seed 0: pan_us06_shape's
  socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{25C,10C,0C,m10C,m20C}_US06.csv --capacity-ah 2.77 -q --seed 1 --candidates 1 \\
      --shape $sh -o $O/pan_us06_s1_$sh.toml
  socd evaluate --cell $O/pan_us06_s1_$sh.toml $(ls $P/pan18650pf_{25C,10C,0C,m10C,m20C}_*.csv | grep -v -e HPPC -e US06) \\
      --estimator fomiukf --no-bar -q --json $O/pan_us06_s1_$sh.json
done
# the HPPC fits are hppc_seed_spread's (pan_s0, pan_s1: each) and hppc_seed_spread_shape's (panord_s0, panord_s1: orders)
G=""; for sh in each orders; do
  for c in Chen2020 Mohtat2020 Marquis2019; do t=_s0_each; [ $sh = orders ] && t=_orders
    G="$G $sh=out/unseen_cell/$c${t}_eval.json@$c $sh=out/unseen_cell/${c}_s1_${sh}_eval.json@$c"; done
  for c in Ai2020 OKane2022 Ecker2015; do t=_s0_each; [ $sh = orders ] && t=_orders
    G="$G $sh=out/unseen_more/$c${t}_eval.json@$c $sh=out/unseen_more/${c}_s1_${sh}_eval.json@$c"; done
  u0=$O/pan_us06_s0_$sh.json
  h=pan_s; [ $sh = orders ] && h=panord_s
  G="$G $sh=$u0@panasonic $sh=$O/pan_us06_s1_$sh.json@panasonic $sh=out/seeds/${h}0.json@panasonic $sh=out/seeds/${h}1.json@panasonic"
done
python -m research.nested_tuning --by cell --estimator fomiukf --reference each --exclude _10C_trise $G \\
    --json out/shape_seeds.json""",
          nested_table("shape_seeds.json"), 330,
          ("needs:unseen_cell", "needs:unseen_cell_more", "needs:unseen_shape",
           "needs:pan_us06_shape", "needs:hppc_seed_spread", "needs:hppc_seed_spread_shape", "needs:pybamm")),
    Table("fit_file_pick", "characterisation.md", REAL + f"""\
# every multi-temperature profile is --shape orders (the default): unseen_shape's and shape_seeds' fits (seeds 0, 1),
# pan_us06_shape's and shape_seeds' (Panasonic OCV test + US06), hppc_seed_spread_shape's (Panasonic HPPC)
mkdir -p out/fitsel; O=out/fitsel; E="--estimator fomiukf --no-bar -q"
for s in 0 1; do
  socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 --seed $s --candidates 1 -q -o $O/calce_s$s.toml
  socd evaluate --cell $O/calce_s$s.toml $C/calce20r_25C_DST_80soc.csv --full-at 3303 $E --json $O/calce_s$s.json
  socd evaluate --cell $O/calce_s$s.toml {CALCE} $E --json $O/calce_s${{s}}_held.json
  socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis \\
      --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv --seed $s --candidates 1 -q -o $O/a123_s$s.toml
  socd evaluate --cell $O/a123_s$s.toml $A/calce_a123_20C_DST.csv --full-at 4815 $E --json $O/a123_s$s.json
  socd evaluate --cell $O/a123_s$s.toml {A123} $E --json $O/a123_s${{s}}_held.json
done
for c in Chen2020 Mohtat2020 Marquis2019; do
  for s in 0 1; do t=_orders; [ $s = 1 ] && t=_s1_orders
    socd evaluate --cell out/unseen_cell/$c$t.toml out/unseen_cell/${{c}}_{{25C,10C,0C}}_US06.csv $E --json $O/${{c}}_s$s.json; done; done
for c in Ai2020 OKane2022 Ecker2015; do
  for s in 0 1; do t=_orders; [ $s = 1 ] && t=_s1_orders
    socd evaluate --cell out/unseen_more/$c$t.toml out/unseen_more/${{c}}_{{25C,10C}}_US06.csv $E --json $O/${{c}}_s$s.json; done; done
socd evaluate --cell out/shape_seeds/pan_us06_s0_orders.toml $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_US06.csv $E --json $O/panus06_s0.json
socd evaluate --cell out/shape_seeds/pan_us06_s1_orders.toml $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_US06.csv $E --json $O/panus06_s1.json
for s in 0 1; do
  socd evaluate --cell out/seeds/panord_s$s.toml $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_HPPC.csv $E --json $O/panhppc_s$s.json; done
G=""
pair() {{  # CELL FIT0 HELD0 FIT1 HELD1: both seeds, and the seed whose filter reads its fit files best, twice
  p=$(python -m research.fit_file_pick $2:$3 $4:$5)
  G="$G single=$3@$1 single=$5@$1 pick=$p@$1 pick=$p@$1"
}}
pair calce $O/calce_s0.json $O/calce_s0_held.json $O/calce_s1.json $O/calce_s1_held.json
pair a123 $O/a123_s0.json $O/a123_s0_held.json $O/a123_s1.json $O/a123_s1_held.json
for c in Chen2020 Mohtat2020 Marquis2019; do
  pair $c $O/${{c}}_s0.json out/unseen_cell/${{c}}_orders_eval.json $O/${{c}}_s1.json out/unseen_cell/${{c}}_s1_orders_eval.json; done
for c in Ai2020 OKane2022 Ecker2015; do
  pair $c $O/${{c}}_s0.json out/unseen_more/${{c}}_orders_eval.json $O/${{c}}_s1.json out/unseen_more/${{c}}_s1_orders_eval.json; done
pair panasonic $O/panus06_s0.json out/shape_seeds/pan_us06_s0_orders.json $O/panus06_s1.json out/shape_seeds/pan_us06_s1_orders.json
pair panasonic $O/panhppc_s0.json out/seeds/panord_s0.json $O/panhppc_s1.json out/seeds/panord_s1.json
python -m research.nested_tuning --by cell --estimator fomiukf --reference single --exclude {TUNING_EXCLUDE} $G \\
    --json out/fit_file_pick.json""",
          nested_table("fit_file_pick.json"), 60,
          ("needs:unseen_shape", "needs:shape_seeds", "needs:pan_us06_shape", "needs:hppc_seed_spread_shape",
           "needs:pybamm")),
    Table("slow_order", "characterisation.md", """\
# every fit here --shape each, the default when this ran; the fits without the bound are unseen_shape's (seed 0)
# and shape_seeds' (seed 1)
python -m research.unseen_cell run --cells OKane2022,Ecker2015 --ambients 25,10 --workdir out/unseen_more \\
    --estimators fomiukf --profile-tag _so6_s0 --refit --fit-flags="--min-slow-order 0.6 --shape each"
python -m research.unseen_cell run --cells OKane2022 --ambients 25,10 --workdir out/unseen_more \\
    --estimators fomiukf --profile-tag _so6_s1 --refit --fit-flags="--min-slow-order 0.6 --seed 1 --candidates 1 --shape each"
for s in 0 1; do
  python -m research.unseen_cell run --cells Chen2020 --estimators fomiukf --profile-tag _so6_s$s --refit \\
      --fit-flags="--min-slow-order 0.6 --seed $s --candidates 1 --shape each"
done""",
          runs_table((("`Chen2020` seed 0, `--min-slow-order 0.3` (default)", "unseen_cell/Chen2020_s0_each_eval.json"),
                      ("`Chen2020` seed 0, `--min-slow-order 0.6`", "unseen_cell/Chen2020_so6_s0_eval.json"),
                      ("`Chen2020` seed 1, `--min-slow-order 0.3` (default)", "unseen_cell/Chen2020_s1_each_eval.json"),
                      ("`Chen2020` seed 1, `--min-slow-order 0.6`", "unseen_cell/Chen2020_so6_s1_eval.json"),
                      ("`OKane2022` seed 0, `--min-slow-order 0.3` (default)", "unseen_more/OKane2022_s0_each_eval.json"),
                      ("`OKane2022` seed 0, `--min-slow-order 0.6`", "unseen_more/OKane2022_so6_s0_eval.json"),
                      ("`OKane2022` seed 1, `--min-slow-order 0.3` (default)", "unseen_more/OKane2022_s1_each_eval.json"),
                      ("`OKane2022` seed 1, `--min-slow-order 0.6`", "unseen_more/OKane2022_so6_s1_eval.json"),
                      ("`Ecker2015` seed 0, `--min-slow-order 0.3` (default)", "unseen_more/Ecker2015_s0_each_eval.json"),
                      ("`Ecker2015` seed 0, `--min-slow-order 0.6`", "unseen_more/Ecker2015_so6_s0_eval.json")),
                     UNSEEN_GROUPS),
          90, ("needs:unseen_cell", "needs:unseen_cell_more", "needs:shape_seeds", "needs:pybamm")),
    Table("slow_order_loco", "characterisation.md", REAL + f"""\
# --min-slow-order 0.6 against the default (0.3, --min-order's) on every characterisation, seed 0, and seed 1 where
# the slow_order table has it, all with --shape each (the default when this ran); the runs at 0.3 are char_calce's and
# char_a123's fits, hppc_seed_spread's (pan_s0), shape_seeds' and unseen_shape's
mkdir -p out/slow_order; O=out/slow_order; E="--estimator fomiukf --no-bar -q"
socd evaluate --cell out/s25/calce.toml {CALCE} $E --json $O/calce_so3.json
socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 --min-slow-order 0.6 -q -o $O/calce_so6.toml
socd evaluate --cell $O/calce_so6.toml {CALCE} $E --json $O/calce_so6.json
socd evaluate --cell out/s25/a123.toml {A123} $E --json $O/a123_so3.json
socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv \\
    --min-slow-order 0.6 -q -o $O/a123_so6.toml
socd evaluate --cell $O/a123_so6.toml {A123} $E --json $O/a123_so6.json
socd fit $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_HPPC.csv --capacity-ah 2.77 --full-at 0 --min-slow-order 0.6 --shape each -q -o $O/pan_hppc_so6.toml
socd evaluate --cell $O/pan_hppc_so6.toml $(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v -e HPPC -e trise) $E \\
    --json $O/pan_hppc_so6.json
socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_US06.csv --capacity-ah 2.77 --min-slow-order 0.6 --shape each -q \\
    -o $O/pan_us06_so6.toml
socd evaluate --cell $O/pan_us06_so6.toml $(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v -e HPPC -e US06) $E \\
    --json $O/pan_us06_so6.json
python -m research.unseen_cell run --cells Mohtat2020,Marquis2019 --estimators fomiukf --profile-tag _so6_s0 --refit \\
    --fit-flags="--min-slow-order 0.6 --shape each"
python -m research.unseen_cell run --cells Ai2020 --ambients 25,10 --workdir out/unseen_more --estimators fomiukf \\
    --profile-tag _so6_s0 --refit --fit-flags="--min-slow-order 0.6 --shape each"
G="so3=$O/calce_so3.json@calce so6=$O/calce_so6.json@calce so3=$O/a123_so3.json@a123 so6=$O/a123_so6.json@a123"
G="$G so3=out/seeds/pan_s0.json@panasonic so3=out/shape_seeds/pan_us06_s0_each.json@panasonic"
G="$G so6=$O/pan_hppc_so6.json@panasonic so6=$O/pan_us06_so6.json@panasonic"
for c in Chen2020 OKane2022; do d=unseen_cell; [ $c = OKane2022 ] && d=unseen_more
  G="$G so3=out/$d/${{c}}_s0_each_eval.json@$c so3=out/$d/${{c}}_s1_each_eval.json@$c"
  G="$G so6=out/$d/${{c}}_so6_s0_eval.json@$c so6=out/$d/${{c}}_so6_s1_eval.json@$c"; done
for c in Mohtat2020 Marquis2019 Ai2020 Ecker2015; do d=unseen_cell; [ $c = Ai2020 -o $c = Ecker2015 ] && d=unseen_more
  G="$G so3=out/$d/${{c}}_s0_each_eval.json@$c so6=out/$d/${{c}}_so6_s0_eval.json@$c"; done
python -m research.nested_tuning --by cell --estimator fomiukf --reference so3 --exclude {TUNING_EXCLUDE} $G \\
    --json out/slow_order_loco.json""",
          nested_table("slow_order_loco.json"), 120,
          ("needs:char_calce", "needs:char_a123", "needs:hppc_seed_spread", "needs:shape_seeds", "needs:slow_order",
           "needs:unseen_cell", "needs:unseen_cell_more", "needs:pybamm")),
    Table("starts_other_cells", "characterisation.md", REAL + f"""\
mkdir -p out/starts
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
E="--estimator fomiukf -q"
socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 --starts 4 -q -o out/starts/calce_k4.toml
socd evaluate --cell out/starts/calce_k4.toml {CALCE} $E --json out/starts/calce_k4.json
socd fit $A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --hysteresis \\
    --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv --starts 4 -q -o out/starts/a123_k4.toml
socd evaluate --cell out/starts/a123_k4.toml {A123} $E --json out/starts/a123_k4.json
socd fit $D/ocv/ocv_pan18650pf_25C.csv $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_US06.csv --capacity-ah 2.77 --starts 4 \\
    -q -o out/starts/panus06_k4.toml
socd evaluate --cell out/starts/panus06_k4.toml $(echo $PANX | tr ' ' '\\n' | grep -v US06) $E --json out/starts/panus06_k4.json""",
          lambda out: runs_table((("CALCE, DST file, default", "fitopt/calce_auto.json"),
                                  ("CALCE, DST file, `--starts 4`", "starts/calce_k4.json"),
                                  ("A123, DST file, default", "fitopt/a123s0_auto.json"),
                                  ("A123, DST file, `--starts 4`", "starts/a123_k4.json"),
                                  ("Panasonic, OCV test + US06, default", "fitopt/panus06_auto.json"),
                                  ("Panasonic, OCV test + US06, `--starts 4`", "starts/panus06_k4.json")),
                                 (("CALCE 25 °C", r"calce20r"), ("A123 20 °C", r"calce_a123"))
                                 + tuple((f"Panasonic {label}", "pan18650pf" + pattern) for label, pattern in PAN_GROUPS))(out),
          40, ("needs:loco_fit_options",)),
    Table("joint_ocv_smoothing", "characterisation.md", REAL + f"""\
mkdir -p out/smooth
E="--estimator fomiukf -q"
HPPC="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_HPPC.csv) --capacity-ah 2.77 --full-at 0"
PANX="$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v HPPC)"
for w in 1 0.01; do   # the Panasonic pulse-test fits take minutes: both at once
  (socd fit $HPPC --ocv-smoothing $w -q -o out/smooth/pan_hppc_$w.toml
   socd evaluate --cell out/smooth/pan_hppc_$w.toml $PANX $E --json out/smooth/pan_hppc_$w.json) &
done
for w in 0.01 0.1 1; do
  socd fit $C/calce20r_25C_DST_80soc.csv --full-at 3303 --capacity-ah 1.999 --ocv-smoothing $w -q -o out/smooth/calce_$w.toml
  socd evaluate --cell out/smooth/calce_$w.toml {CALCE} $E --json out/smooth/calce_$w.json
done
wait""",
          lambda out: "\n\n".join(
              f"{title}:\n\n" + runs_table(tuple((f"{cell}, `--ocv-smoothing {w}`{' (default)' if w == '0.01' else ''}",
                                                  f"smooth/{tag}_{w}.json")
                                                 for cell, tag, ws in (("CALCE, DST file", "calce", ("0.01", "0.1", "1")),
                                                                       ("Panasonic, HPPC alone", "pan_hppc", ("0.01", "1")))
                                                 for w in ws),
                                           (("CALCE 25 °C", r"calce20r"),)
                                           + tuple((f"Panasonic {label}", "pan18650pf" + pattern)
                                                   for label, pattern in PAN_GROUPS), estimator)(out)
              for title, estimator in (("`fomiukf` on the profile", "fomiukf"),
                                       ("`ecm2rc-ekf` on the profile's 2-RC fit, whose OCV is the same joint table",
                                        "ecm2rc-ekf"))),
          12),
    Table("starts_pulse_cells", "characterisation.md", """\
# the default rows are unseen_cell_hppc's
python -m research.unseen_cell run --fit-drive HPPC --profile-tag _hppc_k4 --fit-flags="--starts 4" --refit""",
          runs_table(tuple((f"`{c}`, {label}", f"unseen_cell/{c}_hppc{tag}_eval.json")
                           for c in UNSEEN_CELLS for label, tag in (("default", ""), ("`--starts 4`", "_k4"))),
                     UNSEEN_GROUPS),
          25, ("needs:unseen_cell_hppc", "needs:pybamm")),
    Table("unseen_cell_lfp", "characterisation.md", """\
W=out/unseen_lfp
python -m research.unseen_cell build --cells Prada2013 --ambients 25 --workdir $W
python -m research.unseen_cell run --cells Prada2013 --ambients 25 --workdir $W --refit   # the issue's two commands
python -m research.two_rc_point $W/Prada2013.toml $W/Prada2013_2rc.toml
socd evaluate --cell $W/Prada2013_2rc.toml $(ls $W/Prada2013_25C_*.csv | grep -v -e US06 -e _ocv -e HPPC) \\
    --estimator fomiukf --no-bar -q --json $W/Prada2013_2rc_eval.json""",
          lambda out: "\n\n".join((
              "`socd fit` with no other flag, then `socd evaluate`:\n\n"
              + unseen_table("unseen_lfp", ("Prada2013",), "", (("25 °C", r"_25C_"),))(out),
              "`fomiukf` on the same profile's 2-RC point (`research.two_rc_point`), mean SOC RMSE after 600 s, %:\n\n"
              + runs_table((("fractional point", "unseen_lfp/Prada2013_eval.json"),
                            ("its 2-RC point", "unseen_lfp/Prada2013_2rc_eval.json")),
                           (("25 °C", r"_25C_"),))(out))), 5, ("needs:pybamm",)),
    Table("fit_quality", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2
python -m research.unseen_cell build --cells Prada2013 --ambients 25 --workdir out/unseen_lfp
rm -f out/fit_quality/fit_quality.json
python -m research.fit_quality run --jobs 2""",
          lambda out: tool("fit_quality").markdown(_read(out, "fit_quality/fit_quality.json")), 40,
          ("needs:unseen_cell", "needs:unseen_cell_lfp", "needs:pybamm")),
    Table("fit_quality_capacity", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2
rm -f out/fit_quality/capacity_sweep.json
python -m research.fit_quality capacity --jobs 2""",
          lambda out: tool("fit_quality").capacity_markdown(_read(out, "fit_quality/capacity_sweep.json")), 25,
          ("needs:unseen_cell", "needs:pybamm")),
    Table("unseen_cell_cold", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2 --cells Chen2020,Mohtat2020 --ambients -10
python -m research.unseen_cell run --cells Chen2020,Mohtat2020 --ambients 25,10,0,-10 --profile-tag _m10 --refit""",
          unseen_table("unseen_cell", ("Chen2020", "Mohtat2020"), "_m10", UNSEEN_GROUPS + (("−10 °C", r"_m10C_"),)),
          20, ("needs:unseen_cell", "needs:pybamm")),
    Table("unseen_cell_hysteresis", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2 --hysteresis-mv 10 --workdir out/unseen_cell_hys
python -m research.unseen_cell run --refit --workdir out/unseen_cell_hys""",
          unseen_table("unseen_cell_hys"), 15, ("needs:pybamm",)),
    Table("unseen_cell_40", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2 --ambients 40
python -m research.unseen_cell run --ambients 40,25,10,0 --ocv-ambients 25,10,0 --profile-tag _40 --refit""",
          unseen_table("unseen_cell", tag="_40", groups=(("40 °C (no OCV test)", r"_40C_"),) + UNSEEN_GROUPS),
          25, ("needs:unseen_cell", "needs:pybamm")),
    Table("unseen_cell_shape", "characterisation.md", """\
python -m research.unseen_cell build --jobs 2 --cells Chen2020,Mohtat2020 --ambients 40,-10,-20
python -m research.unseen_cell run --cells Chen2020,Mohtat2020 --ambients 40,25,10,0,-10,-20 --ocv-ambients 25,10,0 \\
    --profile-tag _shape --refit""",
          unseen_table("unseen_cell", ("Chen2020", "Mohtat2020"), "_shape",
                       (("40 °C (no OCV test)", r"_40C_"),) + UNSEEN_GROUPS
                       + (("−10 °C (no OCV test)", r"_m10C_"), ("−20 °C (no OCV test)", r"_m20C_"))),
          30, ("needs:unseen_cell", "needs:pybamm")),
    Table("fit_vs_2rc_point", "characterisation.md", REAL + """\
A123_FIT="$A/calce_a123_20C_DST.csv --full-at 4815 --capacity-ah 1.041 --ocv $D/ocv/ocv_a123_20C_charge_soc_table.csv -q"
socd fit $A123_FIT --hysteresis --no-kinetics -o out/s25/a123_hys_nokin.toml   # out/s25/a123.toml: char_a123
socd fit $A123_FIT -o out/s25/a123_nohys.toml
socd fit $A123_FIT --no-kinetics -o out/s25/a123_nohys_nokin.toml
python -m research.two_rc_point out/s25/a123.toml out/s25/a123_2rc.toml
for v in a123 a123_hys_nokin a123_nohys a123_nohys_nokin a123_2rc; do
  socd evaluate --cell out/s25/$v.toml $A/calce_a123_20C_{DST,FUDS,US06}.csv --full-at 4815 --full-at 4478 --full-at 4436 \\
      --estimator fomiukf --no-bar -q --json out/s25/pt_$v.json
done
python -m research.two_rc_point out/s25/pan_hppc.toml out/s25/pan_hppc_2rc.toml   # out/s25/pan_hppc.toml: char_pan_hppc
for v in pan_hppc pan_hppc_2rc; do
  socd evaluate --cell out/s25/$v.toml $(ls $P/pan18650pf_{10C,m10C,m20C}_*.csv | grep -v trise) \\
      --estimator fomiukf --no-bar -q --json out/s25/pt_$v.json
done""",
          lambda out: runs_table(
              (("A123 `--hysteresis` (`char_a123`'s command)", "s25/pt_a123.json"),
               ("A123 `--hysteresis --no-kinetics`", "s25/pt_a123_hys_nokin.json"),
               ("A123 default flags (no hysteresis)", "s25/pt_a123_nohys.json"),
               ("A123 no hysteresis, `--no-kinetics`", "s25/pt_a123_nohys_nokin.json"),
               ("A123 its 2-RC point (orders 1, no hysteresis)", "s25/pt_a123_2rc.json")),
              (("FUDS, US06 (held out)", r"_a123_20C_(FUDS|US06)"),
               ("DST (the fit file)", r"_a123_20C_DST")))(out) + "\n\n" + runs_table(
              (("Panasonic HPPC fit", "s25/pt_pan_hppc.json"),
               ("Panasonic HPPC fit, every point its 2-RC point", "s25/pt_pan_hppc_2rc.json")),
              tuple((f"{t} {what}", rf"_{key}_{pat}") for t, key in (("10 °C", "10C"), ("−10 °C", "m10C"),
                                                                    ("−20 °C", "m20C"))
                    for what, pat in (("drives", "(?!HPPC)"), ("HPPC (fit file)", "HPPC"))))(out),
          35, ("needs:char_a123", "needs:char_pan_hppc")),
    Table("two_rc_point_by_fit_file", "characterisation.md", REAL + f"""\
mkdir -p out/pt2
E="--estimator fomiukf --no-bar -q"
pt() {{  # TAG PROFILE FIT_FILES HELD_OUT_FILES: both profiles on both sets of files
  python -m research.two_rc_point $2 out/pt2/$1_2rc.toml
  socd evaluate --cell $2 $3 $E --json out/pt2/$1_fit.json
  socd evaluate --cell out/pt2/$1_2rc.toml $3 $E --json out/pt2/$1_2rc_fit.json
  socd evaluate --cell $2 $4 $E --json out/pt2/$1_held.json
  socd evaluate --cell out/pt2/$1_2rc.toml $4 $E --json out/pt2/$1_2rc_held.json
}}
(
  pt calce out/s25/calce.toml "$C/calce20r_25C_DST_80soc.csv --full-at 3303" \\
      "$(echo $C/calce20r_25C_{{DST_50soc,FUDS_80soc,FUDS_50soc,US06_50soc,US06_80soc}}.csv) \\
      --full-at 10015 --full-at 9999 --full-at 5080 --full-at 10160 --full-at 9984"
  pt a123 out/s25/a123.toml "$A/calce_a123_20C_DST.csv --full-at 4815" \\
      "$(echo $A/calce_a123_20C_{{FUDS,US06}}.csv) --full-at 4478 --full-at 4436"
  for c in {" ".join(UNSEEN_CELLS)}; do
    pt $c out/unseen_cell/$c.toml "$(ls out/unseen_cell/${{c}}_{{25C,10C,0C}}_US06.csv)" \\
        "$(ls out/unseen_cell/${{c}}_{{25C,10C,0C}}_*.csv | grep -v -e US06 -e HPPC -e _ocv)"
  done
) & first=$!
pt pan_hppc out/s25/pan_hppc.toml "$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_HPPC.csv) --full-at 0" \\
    "$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v -e HPPC -e trise)"
pt pan_us06 out/s25/pan_us06.toml "$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_US06.csv)" \\
    "$(ls $P/pan18650pf_{{25C,10C,0C,m10C,m20C}}_*.csv | grep -v -e HPPC -e US06 -e trise)"
wait $first""",
          fit_file_rule_table, 40,
          ("needs:char_calce", "needs:char_a123", "needs:char_pan_hppc", "needs:char_pan_us06", "needs:unseen_cell")),
    Table("bench", "bench.md", "for k in 1 2 3; do socd bench --cells 200 --json out/bench200_$k.json; done",
          bench_table("bench200_1.json", "bench200_2.json", "bench200_3.json"), 3),
    Table("bench_simulate", "bench.md",
          "for k in 1 2 3; do socd bench --simulate --json out/bench_simulate_$k.json; done",
          simulate_bench_table("bench_simulate_1.json", "bench_simulate_2.json", "bench_simulate_3.json"), 2),
    Table("latency", "bench.md",
          "for k in 1 2 3; do socd bench --latency --cells 200 --rate-hz 10 --seconds 60 --json out/latency200_$k.json; done",
          latency_table("latency200_1.json", "latency200_2.json", "latency200_3.json"), 2),
    Table("demo", "bench.md", """\
P=../shared/data/real/panasonic_18650pf
socd demo --cells 96 --json out/demo96.json --plot out/demo96.png
socd demo --cells 200 --json out/demo200.json --plot out/demo200.png
socd demo --cells 96 --speed 1 --seconds 60 --recording $P/fullrate_10Hz/pan18650pf_25C_US06_10Hz.csv \\
    --json out/demo96_realtime.json --plot out/demo96_realtime.png""",
          demo_table("demo96.json", "demo200.json", "demo96_realtime.json"), 5),
    Table("demo_capacity", "bench.md", """\
socd demo --json out/demo8_cap2.json
socd demo --spread-capacity 0.05 --json out/demo8_cap5.json
socd demo --spread-capacity 0.05 --freeze-capacity --json out/demo8_cap5_frozen.json
SOCD_ESTIMATOR__CAPACITY_ESTIMATION=absolute socd demo --spread-capacity 0.05 --json out/demo8_cap5_absolute.json
for seed in 1 2; do socd demo --spread-capacity 0.05 --seed $seed --json out/demo8_cap5_seed$seed.json; done
socd demo --cells 96 --spread-capacity 0.05 --json out/demo96_cap5.json
# the same drive's current and temperature through the profile's own model (a recording consistent with it)
python -m research.model_drive service/data/pan18650pf_25C_US06.csv -o out/model_us06.csv
for n in 8 96; do
  socd demo --recording out/model_us06.csv --soc0 1 --cells $n --spread-capacity 0.05 --json out/demo${n}_cap5_model.json
  SOCD_ESTIMATOR__CAPACITY_ESTIMATION=absolute socd demo --recording out/model_us06.csv --soc0 1 --cells $n \\
      --spread-capacity 0.05 --json out/demo${n}_cap5_model_absolute.json
done
# the recorded drive on the Panasonic profile today's socd fit writes with the bundled one's command
# (profiles_refit's out/refit/panasonic_18650pf.toml), whose 25 °C OCV row follows the HPPC rests down to empty
socd demo --cell out/refit/panasonic_18650pf.toml --spread-capacity 0.05 --json out/demo8_cap5_refit.json
SOCD_ESTIMATOR__CAPACITY_ESTIMATION=absolute socd demo --cell out/refit/panasonic_18650pf.toml \\
    --spread-capacity 0.05 --json out/demo8_cap5_refit_absolute.json""",
          demo_capacity_table("demo8_cap2.json", "demo8_cap5.json", "demo8_cap5_frozen.json", "demo8_cap5_absolute.json",
                              "demo8_cap5_seed1.json", "demo8_cap5_seed2.json", "demo96_cap5.json",
                              "demo8_cap5_model.json", "demo8_cap5_model_absolute.json", "demo96_cap5_model.json",
                              "demo96_cap5_model_absolute.json", "demo8_cap5_refit.json",
                              "demo8_cap5_refit_absolute.json"), 5, ("needs:profiles_refit",)),
    Table("capacity_bias", "bench.md", """\
# the single recorded cell at the profile's capacity, started at the truth (research.capacity_bias)
python -m research.capacity_bias service/data/pan18650pf_25C_US06.csv --json out/capacity_bias_bundled.json
python -m research.capacity_bias service/data/pan18650pf_25C_US06.csv --cell out/refit/panasonic_18650pf.toml \\
    --json out/capacity_bias_refit.json
python -m research.capacity_bias out/model_us06.csv --json out/capacity_bias_model.json   # demo_capacity's model drive""",
          capacity_bias_table(("recorded, bundled profile", "capacity_bias_bundled.json"),
                              ("recorded, refit profile", "capacity_bias_refit.json"),
                              ("model drive", "capacity_bias_model.json")), 1,
          ("needs:demo_capacity", "needs:profiles_refit")),
    Table("diag_labelled", "diagnose.md", """\
S=../shared/data/synthetic
for f in dst_s101_4e4041 hppc_s102_131537 bjdst_s103_55f05a randomwalk_s104_e90722 hppc_s105_437525 dst_s106_462959 randomwalk_s107_cac951; do
  socd diagnose $S/$f.csv --ocv $S/${f}_ocv.csv \\
    --capacity-ah $(python -c "import json;print(json.load(open('$S/$f.meta.json'))['capacity_ah'])") \\
    --json out/diag_$f.json --report out/report_$f
done""",
          diagnose_table("diag_{}.json", LABELLED, labels="../shared/data/synthetic/labels.json"), 10),
    Table("clean_twin", "diagnose.md", """\
python -m research.clean_twin --data ../shared/data/synthetic --jobs 2 --workdir out/twin --json out/clean_twin.json""",
          clean_twin_table("clean_twin.json"), 13, ("needs:pybamm",)),
    Table("devset_rules", "diagnose.md", """\
python -m research.devset build --jobs 2 --workdir out/devset
python -m research.devset evidence --jobs 2 --workdir out/devset
python -m research.devset labelled --jobs 2 --workdir out/devset
python -m research.devset rules --jobs 2 --workdir out/devset --json out/devset_rules.json""",
          devset_table("devset_rules.json"), 90, ("needs:pybamm",)),
    Table("devset_blind", "diagnose.md", """\
# three cells no rule was chosen on, built as the development set is, read with the product's rule as it ships
B="--cells ORegan2022,Chen2020_composite,Bonkile2024 --workdir out/devset_blind"
python -m research.devset $B build --jobs 2
python -m research.devset $B evidence --jobs 2
python -m research.devset $B --labelled-workdir out/devset_blind/no_labelled rules --product-rule \\
    --json out/devset_blind.json""",
          devset_table("devset_blind.json"), 30, ("needs:pybamm",)),
    Table("devset_rules_wide", "diagnose.md", """\
# the set and its evidence are devset_rules'
python -m research.devset rules --jobs 2 --workdir out/devset --wide-grid --hold direct_max_rise_rel=0.2 \\
    --json out/devset_rules_wide.json""",
          devset_summary_table("devset_rules_wide.json"), 5, ("needs:devset_rules", "needs:pybamm")),
    Table("devset_hysteresis_levels", "diagnose.md", """\
# the set and its evidence are devset_rules'; the other rules held at the product's values
H="--hold min_rel_gain=0.25 --hold min_rel_gain_nominated=0.05 --hold min_abs_gain_noise=1 --hold min_delta_bic=0"
H="$H --hold kinetics_max_i0_c=0.15 --hold relax_min_ratio=0.15 --hold relax_min_z=5 --hold direct_max_rise_rel=0.2"
python -m research.devset rules --workdir out/devset --search-hysteresis $H --json out/devset_hysteresis_levels.json""",
          devset_summary_table("devset_hysteresis_levels.json"), 2, ("needs:devset_rules", "needs:pybamm")),
    Table("devset_lag_std", "diagnose.md", """\
# the set and its evidence are devset_rules'; the other rules held at the product's values
H="--hold min_rel_gain=0.25 --hold min_rel_gain_nominated=0.05 --hold min_abs_gain_noise=1 --hold min_delta_bic=0"
H="$H --hold kinetics_max_i0_c=0.15 --hold relax_min_ratio=0.15 --hold relax_min_z=5 --hold direct_max_rise_rel=0.2"
python -m research.devset rules --workdir out/devset --search-lag-std $H --json out/devset_lag_std.json""",
          devset_summary_table("devset_lag_std.json"), 2, ("needs:devset_rules", "needs:pybamm")),
    Table("validate", "diagnose.md", "python -m research.validate --seeds 3 --workdir out/validate --json out/validate.json",
          validate_table("validate.json"), 8),
    Table("roundtrip", "diagnose.md", "python -m research.roundtrip --workdir out/roundtrip --json out/roundtrip.json",
          roundtrip_table("roundtrip.json"), 5),
    Table("pybamm_walk", "diagnose.md", """\
python -m research.validate_pybamm --hysteresis-start discharge --jobs 2 --workdir out/validate_pybamm \\
    --json out/validate_pybamm.json""", pybamm_table("validate_pybamm.json"), 22, ("needs:pybamm",)),
    Table("pybamm_interleaved", "diagnose.md", """\
python -m research.validate_pybamm --hysteresis-start discharge --split interleaved --jobs 2 \\
    --workdir out/validate_pybamm_i --json out/validate_pybamm_i.json""",
          pybamm_table("validate_pybamm_i.json"), 25, ("needs:pybamm",)),
    Table("pybamm_hppc", "diagnose.md", """\
python -m research.validate_pybamm --drive hppc --hysteresis-start discharge --jobs 2 \\
    --workdir out/validate_pybamm_hppc --json out/validate_pybamm_hppc.json""",
          pybamm_table("validate_pybamm_hppc.json"), 22, ("needs:pybamm",)),
    Table("pybamm_smooth", "diagnose.md", """\
python -m research.validate_pybamm --drive smooth --jobs 2 --workdir out/validate_pybamm_smooth \\
    --json out/validate_pybamm_smooth.json""",
          pybamm_table("validate_pybamm_smooth.json"), 22, ("needs:pybamm",)),
    Table("diag_real", "diagnose.md", REAL + """\
M=configs/cells/panasonic_18650pf.toml
socd diagnose $P/pan18650pf_m20C_trise_Cycle1.csv --cell $M --json out/diag_pan18650pf_m20C_trise_Cycle1.json
socd diagnose $P/pan18650pf_m20C_trise_Cycle1.csv --cell $M --soc0 1.0 \\
    --json out/diag_pan18650pf_m20C_trise_Cycle1_soc0.json
socd diagnose $P/pan18650pf_10C_trise_Cycle1.csv --cell $M --json out/diag_pan18650pf_10C_trise_Cycle1.json
socd diagnose $A/calce_a123_20C_DST.csv --cell configs/cells/calce_a123.toml --json out/diag_calce_a123_20C_DST.json""",
          diagnose_table("diag_{}.json", REAL_DIAG), 3),
)


# -- markdown blocks -----------------------------------------------------------------------------
def replace_block(text: str, kind: str, name: str, body: str, where: str = "markdown") -> str:
    """``text`` with the content between ``<!-- BEGIN kind:name -->`` and its END marker replaced
    by ``body``; :class:`RegenerateError` when the pair is missing or appears twice."""
    begin, end = f"<!-- BEGIN {kind}:{name} -->", f"<!-- END {kind}:{name} -->"
    pattern = re.compile(re.escape(begin) + r"\n.*?" + re.escape(end), re.DOTALL)
    found = pattern.findall(text)
    if len(found) != 1:
        raise RegenerateError(f"{where}: expected one '{begin}' … '{end}' pair, found {len(found)}")
    return pattern.sub(lambda _m: f"{begin}\n{body.rstrip()}\n{end}", text)


def command_block(table: Table) -> str:
    return f"```sh\n{table.script}\n```"


def table_block(table: Table, rendered: str, when: dt.datetime, commit: str) -> str:
    stamp = when.strftime("%Y-%m-%d %H:%M UTC")
    return (f"{rendered}\n\n_Produced {stamp} at commit {commit} by "
            f"`python docs/results/regenerate.py --only {table.name}`._")


def write_blocks(path: Path, blocks: list[tuple[str, str, str]]) -> None:
    """Replace every ``(kind, name, body)`` in ``path``; nothing is written if any marker is missing."""
    text = path.read_text()
    for kind, name, body in blocks:
        text = replace_block(text, kind, name, body, where=str(path))
    path.write_text(text)


# -- running -------------------------------------------------------------------------------------
def run_commands(table: Table, log_dir: Path) -> None:
    """Run ``table``'s script from the repository root; output to ``log_dir/<name>.log``."""
    prelude = (f'PY={sys.executable!r}\nsocd() {{ "$PY" -m service.cli "$@"; }}\n'
               'python() { "$PY" "$@"; }\nmkdir -p out\n')
    log = log_dir / f"{table.name}.log"
    with log.open("w") as fh:
        done = subprocess.run(["bash", "-euo", "pipefail", "-c", prelude + table.script],
                              cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, check=False)
    if done.returncode != 0:
        tail = log.read_text().strip().splitlines()[-1:] or ["(no output)"]
        raise RegenerateError(f"{table.name}: a command failed with status {done.returncode} "
                              f"(log {log}): {tail[0]}")


def _commit() -> str:
    got = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=False)
    return got.stdout.strip() or "unknown"


def select(names: list[str] | None) -> list[Table]:
    if not names:
        return list(TABLES)
    known = {t.name: t for t in TABLES}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise RegenerateError(f"--only: unknown table(s) {', '.join(unknown)}; known: {', '.join(known)}")
    return [known[n] for n in names]


def waves(tables: list[Table]) -> list[list[Table]]:
    """``tables`` in the order they may run: each wave after every table its ``needs:`` tags name
    among ``tables`` (a table that reads another's files must not start while that one writes
    them).  A need that is not a selected table (one left out of ``--only``, or a package such as
    ``pybamm``) holds nothing back.  A cycle is an error."""
    names = {t.name for t in tables}
    done: set[str] = set()
    left = list(tables)
    out: list[list[Table]] = []
    while left:
        ready = [t for t in left if all(n in done for n in needs(t) if n in names)]
        if not ready:
            raise RegenerateError(f"needs: tags form a cycle among {', '.join(t.name for t in left)}")
        out.append(ready)
        done |= {t.name for t in ready}
        left = [t for t in left if t.name not in done]
    return out


def needs(table: Table) -> list[str]:
    """What ``table``'s ``needs:`` tags name: tables whose files it reads, or packages."""
    return [tag.removeprefix("needs:") for tag in table.tags if tag.startswith("needs:")]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python docs/results/regenerate.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", metavar="NAME", help="a table to regenerate (repeatable; see --list)")
    ap.add_argument("--jobs", type=int, default=1, help="tables whose commands run at once (default 1); a table "
                    "waits for the selected tables it needs (the needs: column of --list)")
    ap.add_argument("--list", action="store_true", help="list the tables and stop")
    ap.add_argument("--commands-only", action="store_true", help="rewrite the command blocks only; run nothing")
    ap.add_argument("--render-only", action="store_true", help="render from the JSON already in out/; run nothing")
    args = ap.parse_args(argv)
    try:
        tables = select(args.only)
        if args.list:
            for t in tables:
                print(f"{t.name:28s} {t.doc:18s} ~{t.minutes:g} min {' '.join(t.tags)}")
            return 0
        if args.jobs < 1:
            raise RegenerateError("--jobs must be 1 or more")
        for doc in sorted({t.doc for t in tables}):  # every marker present before anything runs
            path = RESULTS / doc
            if not path.is_file():
                raise RegenerateError(f"{path}: missing")
            text = path.read_text()
            for t in (t for t in tables if t.doc == doc):
                replace_block(text, "command", t.name, "", where=str(path))
                if t.render is not None:
                    replace_block(text, "table", t.name, "", where=str(path))
        if not (args.commands_only or args.render_only):
            log_dir = ROOT / OUT / "regenerate_logs"
            log_dir.mkdir(parents=True, exist_ok=True)
            with ThreadPoolExecutor(max_workers=args.jobs) as pool:
                for wave in waves(tables):
                    for t, _ in zip(wave, pool.map(lambda t: run_commands(t, log_dir), wave)):
                        print(f"ran {t.name}", file=sys.stderr)
        when, commit = dt.datetime.now(dt.UTC), _commit()
        blocks: dict[str, list[tuple[str, str, str]]] = {}  # every table rendered before any file is written
        for t in tables:
            blocks.setdefault(t.doc, []).append(("command", t.name, command_block(t)))
            if t.render is not None and not args.commands_only:
                blocks[t.doc].append(("table", t.name, table_block(t, t.render(ROOT / OUT), when, commit)))
        for doc, doc_blocks in sorted(blocks.items()):
            write_blocks(RESULTS / doc, doc_blocks)
            print(f"wrote {RESULTS / doc}", file=sys.stderr)
    except RegenerateError as exc:
        print(f"regenerate: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
