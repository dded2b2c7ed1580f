"""rest_check: the truth against the OCV table at the ends of rests, on recordings simulated by
the model (where the OCV table is exact) and through its command line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import make_nmc_profile, write_recording_csv

from research.rest_check import main, read_rests
from service.cell.profile import save_profile
from service.cell.trajectory import simulate
from service.cell.truth import truth_and_start
from service.recording import load_recording

pytestmark = pytest.mark.research


def _two_rests(tmp_path: Path, soc0: float = 1.0) -> Path:
    """1C discharge 1200 s, rest 1800 s, twice; the model's voltage, no soc_true column."""
    profile = make_nmc_profile()
    one_c = profile.capacity_ah
    i = np.concatenate([np.zeros(60), np.full(1200, one_c), np.zeros(1800), np.full(1200, one_c), np.zeros(1800)])
    t = np.arange(i.size, dtype=float)
    temp = np.full(i.size, 25.0)
    v, _ = simulate(profile, t, i, temp, soc0)
    return write_recording_csv(tmp_path / "two_rests.csv", t, i, v, temp)


def _readings(path: Path, capacity_scale: float = 1.0):
    profile = make_nmc_profile()
    profile = profile.model_copy(update={"capacity_ah": profile.capacity_ah * capacity_scale})
    part, truth = truth_and_start(load_recording(path), profile.capacity_ah, None)
    return read_rests(part, truth, profile, min_rest_s=30.0)


def test_the_models_own_recording_agrees_with_its_truth(tmp_path: Path) -> None:
    r = _readings(_two_rests(tmp_path))
    assert [round(x.rest_s) for x in r] == [59, 1799, 1799]
    # the opening rest (full) and the two rests after a third of the charge each
    assert [x.soc_true for x in r] == pytest.approx([1.0, 2 / 3, 1 / 3], abs=2e-3)
    for x in r:
        assert abs(x.diff_pct) < 1.0, x
        assert abs(x.tail_mv_per_min) < 1.0, x


def test_a_truth_with_the_wrong_capacity_shows_a_growing_difference(tmp_path: Path) -> None:
    """Truth counted with 10 % too much capacity sits high by a third x (1 - 1/1.1) per 1C-third drawn."""
    path = _two_rests(tmp_path)
    right = _readings(path)
    wrong = _readings(path, capacity_scale=1.1)
    shift = [w.diff_pct - r.diff_pct for w, r in zip(wrong, right)]
    drawn = np.array([0.0, 1 / 3, 2 / 3])
    expected = -100 * drawn * (1 - 1 / 1.1)
    assert shift == pytest.approx(expected, abs=0.05)


def test_hysteresis_is_read_on_the_branch_of_the_last_current(tmp_path: Path) -> None:
    """A profile with U_H: after a discharge the rest voltage is read as OCV − U_H."""
    path = _two_rests(tmp_path)
    profile = make_nmc_profile()
    with_h = profile.model_copy(update={"hysteresis": profile.hysteresis.model_copy(update={"u_h_max_v": 0.02})})
    part, truth = truth_and_start(load_recording(path), profile.capacity_ah, None)
    r = read_rests(part, truth, with_h, min_rest_s=30.0)
    assert [x.u_h_v for x in r] == [0.0, -0.02, -0.02]  # the opening rest has no current before it


def test_cli_table_json_and_errors(tmp_path: Path, capsys) -> None:
    path = _two_rests(tmp_path)
    cell = tmp_path / "nmc.toml"
    save_profile(make_nmc_profile(), cell)
    out = tmp_path / "r" / "rests.json"
    assert main([str(path), "--cell", str(cell), "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert table.count("| two_rests |") == 2  # the 59 s opening rest is below the 240 s default
    doc = json.loads(out.read_text())
    assert len(doc["rests"]) == 2 and doc["min_rest_s"] == 240.0
    assert main([str(path), "--cell", str(cell), "--min-rest-s", "30"]) == 2
    assert "--min-rest-s" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.csv"), "--cell", str(cell)]) == 2
    assert "missing.csv" in capsys.readouterr().err
    assert main([str(path), "--cell", str(tmp_path / "nope.toml")]) == 2
    assert "nope.toml" in capsys.readouterr().err
    assert main([str(path), str(path), "--cell", str(cell), "--full-at", "0", "--full-at", "1", "--full-at", "2"]) == 2
    assert "--full-at" in capsys.readouterr().err


def test_a_rest_logged_with_two_samples_has_no_tail(tmp_path: Path, capsys) -> None:
    """A123-style log: the end rest is one sample when the current stops and one 300 s later."""
    profile = make_nmc_profile()
    t = np.concatenate([np.arange(600.0), [600.0, 900.0]])
    i = np.concatenate([np.full(600, profile.capacity_ah), [0.0, 0.0]])
    temp = np.full(t.size, 25.0)
    v, _ = simulate(profile, t, i, temp, 1.0)
    path = write_recording_csv(tmp_path / "sparse.csv", t, i, v, temp)
    cell = tmp_path / "nmc.toml"
    save_profile(profile, cell)
    out = tmp_path / "r.json"
    assert main([str(path), "--cell", str(cell), "--json", str(out)]) == 0
    (row,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| sparse |")]
    assert row.endswith("| – |")
    (reading,) = json.loads(out.read_text())["rests"]
    assert reading["tail_mv_per_min"] is None and reading["rest_s"] == 300.0
