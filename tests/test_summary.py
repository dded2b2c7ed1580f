"""README tables from ``socd evaluate --json`` files (``python -m research.summary``)."""

from __future__ import annotations

import json

import pytest

from research.summary import main, table

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
