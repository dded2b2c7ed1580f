"""``socd demo`` runs with small settings and its JSON has the promised keys and sane values."""

from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from service.cli import main
from service.demo import DemoResult, summary_text

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "panasonic_18650pf"
KEYS = {"cells", "frames_in", "frames_rejected", "values_rejected", "soc_rmse_pct", "zenoh_messages",
        "can_frames_out"}


def _check(out: Path, cells: int) -> dict:
    data = json.loads(out.read_text())
    assert KEYS <= set(data)
    assert data["cells"] == cells and len(data["per_cell_rmse_pct"]) == cells
    assert data["frames_in"] > 100 and data["frames_rejected"] == 0 and data["values_rejected"] == 0
    assert data["steps"] >= data["samples"] - 2 > 50
    assert 0.0 <= data["soc_rmse_pct"] < 10.0
    assert data["zenoh_messages"] > 0 and data["zenoh_by_kind"]["soc"] >= cells
    assert data["can_frames_out"] > 0 and data["can_frames_seen"] == data["can_frames_out"]
    assert all(0.0 <= s <= 100.0 for s in data["final_soc_pct"])
    assert len(data["capacity_err_pct"]) == cells and all(abs(x) < 31 for x in data["capacity_err_pct"])
    return data


def test_demo_on_the_bundled_drive_cycle(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from service.assets import bundled_recording

    scratch = tmp_path / "tmp"  # the demo's temporary folder (its checkpoint) is removed at the end
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))

    try:
        bundled_recording()
    except FileNotFoundError as exc:
        pytest.skip(str(exc))
    out, plot = tmp_path / "demo.json", tmp_path / "demo.png"
    assert main(["demo", "--cells", "4", "--seconds", "400", "--json", str(out), "--plot", str(plot)]) == 0
    _check(out, 4)
    assert plot.stat().st_size > 10_000
    text = capsys.readouterr().out
    assert "SOC error vs truth" in text and "Zenoh messages received" in text
    assert "truth: the recorded cell starts at 100.0 % SOC, as the bundled drive starts at the end" in text
    assert json.loads(out.read_text())["soc_within_2sigma_pct"] is None  # nothing scored past 600 s
    assert list(scratch.iterdir()) == []
    # a fast replay that filled the publisher's queue says why publish_drops is up; in real time it is a fault
    result = DemoResult(**json.loads(out.read_text()))
    dropped = replace(result, status_flags={**result.status_flags, "publish_drops": True})
    assert "status flags: publish_drops (the drive ran" in summary_text(dropped)
    assert summary_text(replace(dropped, wall_s=dropped.seconds_replayed)).endswith("status flags: publish_drops")


def test_demo_with_a_given_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    rec = SHARED / "pan18650pf_25C_US06.csv"
    if not rec.is_file():
        pytest.skip(f"{rec} not present")
    out = tmp_path / "demo.json"
    monkeypatch.chdir(tmp_path)  # --no-plot: nothing in the working folder but the JSON asked for
    assert main(["demo", "--cells", "3", "--seconds", "700", "--recording", str(rec), "--json", str(out),
                 "--no-plot"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo.json"]
    data = _check(out, 3)
    assert data["recording"] == rec.name and data["seconds_replayed"] == pytest.approx(700, abs=2)
    # past 600 s the demo says how often the truth lies within the σ the service published
    assert 0.0 <= data["soc_within_2sigma_pct"] <= 100.0
    out = capsys.readouterr().out
    assert "within its published 2σ" in out
    # no --soc0: the truth's start is read from the voltage 1 s into the drive's first pause, and the
    # demo says so (a 0 °C drive read 13 % "error" that was its own truth's, without a word)
    assert data["truth_start"].startswith("read from the OCV at 31 s") and not data["truth_start_settled"]
    assert "still relaxing there: give --soc0" in out


def test_the_shipped_recording_named_starts_as_the_default_demo(tmp_path: Path) -> None:
    """``--recording pan18650pf_25C_US06`` is the demo's own drive: its truth starts full, as without it."""
    from service.assets import bundled_recording

    runs = {}
    for name, extra in (("default", []), ("named", ["--recording", bundled_recording().stem])):
        out = tmp_path / f"{name}.json"
        assert main(["demo", "--cells", "2", "--seconds", "60", "--no-plot", "--json", str(out), *extra]) == 0
        runs[name] = json.loads(out.read_text())
    assert runs["named"]["truth_start"] == runs["default"]["truth_start"]
    assert runs["named"]["truth_start_soc_pct"] == runs["default"]["truth_start_soc_pct"] == 100.0


def test_demo_estimates_with_the_given_cell_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--cell`` replaces the bundled profile (the service estimates with it, the pack is built
    from it): another profile gives other estimates on the same drive; a missing one is named."""
    runs = {}
    for cell in (None, "panasonic_18650pf_nokinetics"):
        out = tmp_path / f"demo_{cell}.json"
        extra = [] if cell is None else ["--cell", cell]
        assert main(["demo", "--cells", "2", "--seconds", "300", "--json", str(out), *extra]) == 0
        runs[cell] = _check(out, 2)
    assert runs[None]["final_soc_pct"] != runs["panasonic_18650pf_nokinetics"]["final_soc_pct"]
    capsys.readouterr()
    assert main(["demo", "--cell", str(tmp_path / "none.toml")]) == 2
    err = capsys.readouterr().err
    assert "none.toml" in err and "bundled profiles, by name: calce_a123, " in err


def test_demo_rejects_bad_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--cells", "0"]) == 2
    assert "--cells" in capsys.readouterr().err
    assert main(["demo", "--speed", "-1"]) == 2


def test_the_replay_stops_where_a_cell_of_the_pack_is_empty() -> None:
    """A 96-cell pack with a 5 % capacity spread built from the bundled drive has cells that would
    be emptied before the recorded cell is: the demo replays up to the first of them, so every
    truth it scores is a SOC in [0, 1]; the 8-cell default pack keeps the whole drive."""
    from replay.pack import SpreadSpec, expand_pack
    from service.assets import bundled_recording
    from service.cell.profile import load_profile
    from service.config import DEFAULT_CELL_PROFILE
    from service.demo import within_every_cell
    from service.recording import load_recording

    profile, rec = load_profile(DEFAULT_CELL_PROFILE), load_recording(bundled_recording())
    spread = SpreadSpec(capacity=0.05, resistance=0.05, soc=0.02, temperature_c=0.5)
    pack = expand_pack(rec, profile, 96, spread, seed=0, start_soc=1.0)
    assert pack.truth_soc.min() < 0  # the whole drive would score impossible truths
    cut, cell = within_every_cell(rec, pack.truth_soc)
    assert cell is not None and len(cut) < len(rec) and pack.truth_soc[len(cut), cell] < 0
    kept = expand_pack(cut, profile, 96, spread, seed=0, start_soc=1.0)
    assert kept.truth_soc.min() >= 0 and kept.truth_soc.max() <= 1
    assert np.array_equal(kept.truth_soc, pack.truth_soc[:len(cut)])  # the same pack, shorter
    default = expand_pack(rec, profile, 8, SpreadSpec(capacity=0.02, resistance=0.05, soc=0.02), seed=0,
                          start_soc=1.0)
    assert within_every_cell(rec, default.truth_soc) == (rec, None)
