"""``socd demo`` runs with small settings and its JSON has the promised keys and sane values."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.cli import main

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "panasonic_18650pf"
KEYS = {"cells", "frames_in", "frames_rejected", "soc_rmse_pct", "zenoh_messages", "can_frames_out"}


def _check(out: Path, cells: int) -> dict:
    data = json.loads(out.read_text())
    assert KEYS <= set(data)
    assert data["cells"] == cells and len(data["per_cell_rmse_pct"]) == cells
    assert data["frames_in"] > 100 and data["frames_rejected"] == 0
    assert data["steps"] >= data["samples"] - 2 > 50
    assert 0.0 <= data["soc_rmse_pct"] < 10.0
    assert data["zenoh_messages"] > 0 and data["zenoh_by_kind"]["soc"] >= cells
    assert data["can_frames_out"] > 0 and data["can_frames_seen"] == data["can_frames_out"]
    assert all(0.0 <= s <= 100.0 for s in data["final_soc_pct"])
    assert len(data["capacity_err_pct"]) == cells and all(abs(x) < 31 for x in data["capacity_err_pct"])
    return data


def test_demo_on_the_bundled_drive_cycle(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from service.demo import bundled_recording

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


def test_demo_with_a_given_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = SHARED / "pan18650pf_25C_US06.csv"
    if not rec.is_file():
        pytest.skip(f"{rec} not present")
    out = tmp_path / "demo.json"
    assert main(["demo", "--cells", "3", "--seconds", "300", "--recording", str(rec), "--json", str(out)]) == 0
    data = _check(out, 3)
    assert data["recording"] == rec.name and data["seconds_replayed"] == pytest.approx(300, abs=2)


def test_demo_rejects_bad_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--cells", "0"]) == 2
    assert "--cells" in capsys.readouterr().err
    assert main(["demo", "--speed", "-1"]) == 2
