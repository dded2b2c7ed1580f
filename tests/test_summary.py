"""README tables from ``socd evaluate --json`` files (``python -m research.summary``)."""

from __future__ import annotations

import json

import pytest

from research.summary import main, paired_difference, table

pytestmark = pytest.mark.research


def _write(path, cell, rows):
    path.write_text(json.dumps({"cell": cell, "results": [
        {"recording": rec, "estimator": est, "soc_rmse_after_600s_pct": v, "v_rmse_mv": 10.0} for rec, est, v in rows]}))


def test_side_by_side_profiles_and_only_filter(tmp_path, capsys):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    _write(a, "configs/cells/slow.toml", [("r1", "fomiukf", 0.5), ("r1", "coulomb", 20.0), ("r2", "fomiukf", 0.3)])
    _write(b, "configs/cells/plain.toml", [("r1", "fomiukf", 0.7), ("r1", "ecm2rc-ekf", 0.9), ("r2", "ecm2rc-ekf", 0.4)])
    full = table(f"{a}+{b}")
    assert "| recording | fomiukf | coulomb | fomiukf (plain) | ecm2rc-ekf (plain) |" in full
    assert "| **mean** | **0.40** | **20.00** | **0.70** | **0.65** |" in full
    assert main(["--only", "fomiukf,ecm2rc-ekf", f"{a}+{b}"]) == 0
    out = capsys.readouterr().out
    assert "| recording | fomiukf | fomiukf (plain) | ecm2rc-ekf (plain) |" in out
    assert "coulomb" not in out
    assert "| r2 | 0.30 | - | 0.40 |" in out


def test_difference_from_the_bar_is_paired_by_recording_and_within_one_profile(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    _write(a, "configs/cells/one.toml", [("r1", "fomiukf", 1.0), ("r1", "ecm2rc-ekf", 0.5),
                                         ("r2", "fomiukf", 2.0), ("r2", "ecm2rc-ekf", 1.0),
                                         ("r3", "fomiukf", 0.5), ("r3", "ecm2rc-ekf", 0.5),
                                         ("r4", "fomiukf", 9.0)])  # r4: no bar, left out of the pairs
    _write(b, "configs/cells/two.toml", [("r1", "fomiukf", 0.2), ("r1", "ecm2rc-ekf", 0.4)])
    diff, se = paired_difference([(1.0, 0.5), (2.0, 1.0), (0.5, 0.5)])
    assert diff == pytest.approx(0.5) and se == pytest.approx(0.5 / 3**0.5)
    assert paired_difference([(1.0, 0.25)]) == (0.75, 0.0)
    # each profile's columns against the bar scored with the same profile
    assert "| Δ vs ecm2rc-ekf ± SE | +0.50 ± 0.29 | - | -0.20 ± 0.00 | - |" in table(f"{a}+{b}")
    # no bar: no difference row
    assert "Δ vs" not in table(str(a), only={"fomiukf"})
