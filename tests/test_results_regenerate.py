"""docs/results/regenerate.py: tables rendered from the JSON real ``socd`` runs write, and written
between the markers of a results file; every table the script knows has its markers in place."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from service.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "docs" / "results" / "regenerate.py"
A123 = ROOT.parent / "shared" / "data" / "real" / "calce_a123"


@pytest.fixture(scope="module")
def regen():
    spec = importlib.util.spec_from_file_location("regenerate", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["regenerate"] = module  # dataclasses resolve the module by name
    spec.loader.exec_module(module)
    return module


def socd(*args: str, tmpdir: Path | None = None) -> None:
    """A real ``socd`` run in its own process (``socd bench`` pins its process to one core); ``tmpdir``:
    its temporary files' folder (``TMPDIR``)."""
    env = None if tmpdir is None else {**os.environ, "TMPDIR": str(tmpdir)}
    done = subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          check=False, env=env)
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def bench_json(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("out")
    socd("bench", "--cells", "3", "--steps", "12", "--reference-steps", "2", "--json", str(out / "bench_small.json"))
    return out / "bench_small.json"


def test_bench_table_carries_the_run_s_figures(regen, bench_json):
    got = json.loads(bench_json.read_text())
    table = regen.bench_table(bench_json.name)(bench_json.parent)
    header, rule, row = table.splitlines()
    assert header.count("|") == rule.count("|") == row.count("|")
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1:4] == [str(got["cells"]), str(got["memory_length"]), str(got["innovation_length"])]
    assert cells[4] == f"{got['cell_steps_per_s']:,.0f}"
    assert cells[5] == f"{got['reference_cell_steps_per_s']:,.0f}"
    assert cells[6] == f"{got['ratio']:.0f}×"


def test_latency_table_carries_the_run_s_figures(regen, tmp_path):
    """A short real ``socd bench --latency`` (the service, a virtual bus, Zenoh on 127.0.0.1):
    every estimate reached the subscriber, and the table shows the run's percentiles; the run's
    checkpoint folder is gone afterwards (each run left one in /tmp)."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    socd("bench", "--latency", "--cells", "8", "--seconds", "2", "--warmup", "1", "--json", str(tmp_path / "lat.json"),
         tmpdir=scratch)
    assert list(scratch.iterdir()) == []
    got = json.loads((tmp_path / "lat.json").read_text())
    assert got["cells"] == 8 and got["samples_measured"] > 0 and got["frames_rejected"] == 0
    assert got["delivered_summary_ms"]["n"] > 0 and got["delivered_last_cell_ms"]["n"] > 0
    table = regen.latency_table("lat.json")(tmp_path)
    header, rule, row = table.splitlines()
    assert header.count("|") == rule.count("|") == row.count("|")
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "8" and cells[5] == f"{got['put_ms']['p50']:.1f} / {got['put_ms']['p99']:.1f}"


def head(src: Path, dst: Path, until_s: float) -> Path:
    """``src``'s header and its rows stamped before ``until_s`` (its first column is ``time_s``), written to ``dst``."""
    header, *rows = src.read_text().splitlines(keepends=True)
    dst.write_text(header + "".join(r for r in rows if float(r.split(",", 1)[0]) < until_s))
    return dst


@pytest.mark.skipif(not A123.is_dir(), reason="needs ../shared/data/real/calce_a123")
def test_evaluate_table_is_the_mean_of_the_run_s_rows(regen, tmp_path, capsys):
    """A real ``socd evaluate`` (in this process) on two CALCE A123 drives, each cut 30 minutes after
    its full charge (the runs score from there, the RMSE after 600 s over the last 20 minutes)."""
    (tmp_path / "rec").mkdir()
    recs = [head(A123 / f"calce_a123_20C_{drive}.csv", tmp_path / "rec" / f"calce_a123_20C_{drive}.csv", full + 1800.0)
            for drive, full in (("FUDS", 4478.0), ("US06", 4436.0))]
    assert main(["evaluate", "--cell", str(ROOT / "configs" / "cells" / "calce_a123.toml"), *map(str, recs),
                 "--full-at", "4478", "--full-at", "4436", "--estimator", "ecm2rc-ekf", "--estimator", "coulomb",
                 "--quiet", "--json", str(tmp_path / "a.json")]) == 0, capsys.readouterr().err
    results = json.loads((tmp_path / "a.json").read_text())["results"]
    table = regen.evaluate_table("a.json")(tmp_path)
    lines = table.splitlines()
    assert lines[2] == "| recording | ecm2rc-ekf | coulomb |"
    ekf = [r["soc_rmse_after_600s_pct"] for r in results if r["estimator"] == "ecm2rc-ekf"]
    assert len(ekf) == 2
    rows = {ln.split("|")[1].strip(): ln for ln in lines[4:]}
    for r in results:
        if r["estimator"] == "ecm2rc-ekf":
            assert f"| {r['soc_rmse_after_600s_pct']:.2f} |" in rows[r["recording"]]
    assert rows["**mean**"].startswith(f"| **mean** | **{sum(ekf) / 2:.2f}** | **20.00** |")


def test_render_only_writes_between_the_markers_and_nowhere_else(regen, bench_json, tmp_path, monkeypatch):
    results = tmp_path / "docs"
    results.mkdir()
    doc = results / "bench.md"
    doc.write_text("# Bench\n\nkept above\n\n<!-- BEGIN command:bench -->\nold\n<!-- END command:bench -->\n\n"
                   "<!-- BEGIN table:bench -->\nold table\n<!-- END table:bench -->\n\nkept below\n")
    out = tmp_path / "out"
    out.mkdir()
    for k in (1, 2, 3):
        (out / f"bench200_{k}.json").write_text(bench_json.read_text())
    monkeypatch.setattr(regen, "RESULTS", results)
    monkeypatch.setattr(regen, "ROOT", tmp_path)
    assert regen.main(["--render-only", "--only", "bench"]) == 0
    text = doc.read_text()
    assert text.startswith("# Bench\n\nkept above\n\n") and text.endswith("\n\nkept below\n")
    assert "old" not in text
    bench = next(t for t in regen.TABLES if t.name == "bench")
    assert f"```sh\n{bench.script}\n```" in text
    assert regen.bench_table("bench200_1.json")(out).splitlines()[2].replace("bench200_1", "bench200_2") in text
    assert "by `python docs/results/regenerate.py --only bench`" in text


def test_a_missing_marker_is_one_error_and_nothing_is_written(regen, tmp_path, monkeypatch, capsys):
    doc = tmp_path / "bench.md"
    before = "<!-- BEGIN command:bench -->\n<!-- END command:bench -->\n"  # no table markers
    doc.write_text(before)
    monkeypatch.setattr(regen, "RESULTS", tmp_path)
    assert regen.main(["--render-only", "--only", "bench"]) == 2
    assert "table:bench" in capsys.readouterr().err
    assert doc.read_text() == before
    with pytest.raises(regen.RegenerateError):
        regen.replace_block(before + before, "command", "bench", "x")


def test_an_unknown_table_is_refused(regen, capsys):
    assert regen.main(["--only", "no_such_table"]) == 2
    assert "unknown table" in capsys.readouterr().err


def test_every_table_has_its_markers_in_its_results_file(regen):
    for t in regen.TABLES:
        text = (SCRIPT.parent / t.doc).read_text()
        kinds = ("command", "table") if t.render is not None else ("command",)
        for kind in kinds:
            assert text.count(f"<!-- BEGIN {kind}:{t.name} -->") == 1, (t.doc, kind, t.name)
            assert text.count(f"<!-- END {kind}:{t.name} -->") == 1, (t.doc, kind, t.name)
        assert f"```sh\n{t.script}\n```" in text, f"{t.doc}: the command block of {t.name} is not the script's"


def test_a_table_waits_for_the_tables_it_needs(regen):
    """``--jobs 2`` must not start a table while a table it reads is still writing: each runs in a
    wave after its selected needs; needs outside the selection do not hold a table back."""
    by_name = {t.name: t for t in regen.TABLES}
    chosen = [by_name[n] for n in ("loco_rest_anchor", "char_joint_ocv", "loco_defaults", "char_calce")]
    waves = [[t.name for t in wave] for wave in regen.waves(chosen)]
    assert waves == [["char_joint_ocv", "char_calce"], ["loco_defaults"], ["loco_rest_anchor"]]
    assert [[t.name for t in w] for w in regen.waves([by_name["loco_rest_anchor"]])] == [["loco_rest_anchor"]]
    a = regen.Table("a", "x.md", "true", None, 1, ("needs:b",))
    b = regen.Table("b", "x.md", "true", None, 1, ("needs:a",))
    with pytest.raises(regen.RegenerateError, match="cycle"):
        regen.waves([a, b])


def test_seed_spread_table_reads_the_fit_logs_and_the_evaluations(regen, tmp_path, nmc_recording, capsys):
    """Two real ``socd fit`` runs (seeds 0 and 1, their logs kept as the table's script keeps them: what
    they wrote to stdout and stderr) and ``socd evaluate`` on each, in this process: the table gives each
    run's SOC RMSE after 600 s and the fit RMSE its log printed, and the averaged row is the mean of the
    runs' figures."""
    rec = nmc_recording(name="spread", duration_s=700, seed=4, soc0=0.95)
    (tmp_path / "seeds").mkdir()
    capsys.readouterr()
    for s in (0, 1):
        stem = tmp_path / "seeds" / f"s{s}"
        rc = main(["fit", "--candidates", "1", str(rec.path), "--capacity-ah", "2.0", "--max-seconds", "1", "--force",
                   "--seed", str(s), "-o", f"{stem}.toml"])
        done = capsys.readouterr()
        assert rc == 0, done.err
        Path(f"{stem}.fitlog").write_text(done.out + done.err)
        assert main(["evaluate", "--cell", f"{stem}.toml", str(rec.path), "--estimator", "fomiukf", "--no-bar",
                     "--quiet", "--json", f"{stem}.json"]) == 0, capsys.readouterr().err
    table = regen.seed_spread_table((("seed 0", "seeds/s0"), ("seed 1", "seeds/s1")), ("25",),
                                    (("all", r"spread"),), averaged=2)(tmp_path)
    lines = table.splitlines()
    assert len(lines) == 5 and lines[1].count("|") == lines[0].count("|")
    soc = []
    for s, line in zip((0, 1), lines[2:4]):
        logged = regen.fit_rmse_by_temperature((tmp_path / "seeds" / f"s{s}.fitlog").read_text())
        (rmse,) = logged.values()
        got = json.loads((tmp_path / "seeds" / f"s{s}.json").read_text())["results"][0]["soc_rmse_after_600s_pct"]
        soc.append(got)
        assert line == f"| seed {s} | {got:.2f} | {rmse:.1f} |"
    assert lines[4] == f"| mean of the 2 rows above | {sum(soc) / 2:.2f} | - |"
