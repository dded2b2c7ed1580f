"""Choosing between profiles by the filter's error on their own fit files (research.fit_file_pick)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from research.fit_file_pick import main

pytestmark = pytest.mark.research


def _results(path: Path, scores: dict[str, float | None], estimator: str = "fomiukf") -> str:
    path.write_text(json.dumps({"cell": "c", "results": [
        {"recording": r, "estimator": estimator, "soc_rmse_after_600s_pct": s} for r, s in scores.items()]}))
    return str(path)


def test_the_pick_reads_the_fit_files_only(tmp_path: Path, capsys) -> None:
    # seed 0 reads its fit files worse (mean 0.8 against 0.5) but its held-out file better: the held-out
    # file must not decide, and a recording without a score after 600 s counts for nothing
    fit0 = _results(tmp_path / "f0.json", {"a": 0.6, "b": 1.0, "short": None})
    fit1 = _results(tmp_path / "f1.json", {"a": 0.4, "b": 0.6})
    held0 = _results(tmp_path / "h0.json", {"x": 0.1})
    held1 = _results(tmp_path / "h1.json", {"x": 0.9})
    assert main([f"{fit0}:{held0}", f"{fit1}:{held1}"]) == 0
    assert capsys.readouterr().out.strip() == held1


def test_other_estimators_in_the_fit_files_do_not_count(tmp_path: Path, capsys) -> None:
    fit0 = tmp_path / "f0.json"
    fit0.write_text(json.dumps({"results": [
        {"recording": "a", "estimator": "fomiukf", "soc_rmse_after_600s_pct": 0.3},
        {"recording": "a", "estimator": "ecm2rc-ekf", "soc_rmse_after_600s_pct": 5.0}]}))
    fit1 = _results(tmp_path / "f1.json", {"a": 0.4})
    assert main([f"{fit0}:h0.json", f"{fit1}:h1.json"]) == 0
    assert capsys.readouterr().out.strip() == "h0.json"


@pytest.mark.parametrize("content", ["not json", json.dumps({"results": []}),
                                     json.dumps({"results": [{"estimator": "ecm2rc-ekf",
                                                              "soc_rmse_after_600s_pct": 0.3}]})])
def test_a_fit_file_result_it_cannot_score_is_named(tmp_path: Path, capsys, content: str) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(content)
    good = _results(tmp_path / "f1.json", {"a": 0.4})
    assert main([f"{bad}:h0.json", f"{good}:h1.json"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "Traceback" not in err
