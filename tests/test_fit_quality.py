"""``research.fit_quality`` reads what ``socd fit --report`` says about each temperature, and judges it
by the product's own rule (the table in docs/results/characterisation.md rests on this)."""

from __future__ import annotations

from pathlib import Path

import pytest

from research.fit_quality import (
    JobResult,
    choose_share_bar,
    fit_rows,
    refusal_kind,
    share_bar_table,
    share_errors,
)
from service.cli import main
from tests.conftest import NMC_CAPACITY_AH


def test_the_fit_report_gives_each_temperatures_figures_and_the_products_verdict(tmp_path: Path, nmc_recording,
                                                                                nmc_ocv_csv: Path) -> None:
    drive = nmc_recording(name="drive", duration_s=1800, seed=5, soc0=0.95)
    out, report = tmp_path / "cell.toml", tmp_path / "fit.json"
    assert main(["fit", "--candidates", "1", str(drive.path), "--ocv", str(nmc_ocv_csv), "--capacity-ah", str(NMC_CAPACITY_AH),
                 "--max-seconds", "3", "--force", "-o", str(out), "--report", str(report)]) == 0
    rows = fit_rows(report)
    assert [r["temp_c"] for r in rows] == [25.0]
    row = rows[0]
    assert 0.0 < row["rmse_mv"] < row["overpotential_rms_mv"]
    assert row["unexplained_share"] == pytest.approx(row["rmse_mv"] / row["overpotential_rms_mv"])
    assert row["refused_by"] is None  # the simulated cell is the model's own


@pytest.mark.parametrize(("message", "kind"), [
    ("25 °C: fit RMSE 72.6 mV is above 68 mV (the larger of 50 mV and 0.5 x the 136 mV RMS overpotential).",
     "poor fit"),
    ("10 °C: fit RMSE 30.0 mV is worse than the textbook 2-RC fit of the same data (20.0 mV ...)", "worse than the 2-RC fit"),
    ("ocv25: --capacity-ah 2.3 is 15% more than the 2 Ah this OCV test's slow branch moved at 25 °C; ...",
     "capacity above the OCV test's"),
    ("drive.csv: no stretch to fit", "drive.csv: no stretch to fit"),
])
def test_a_refusal_is_named_by_what_it_was_about(message: str, kind: str) -> None:
    assert refusal_kind(message) == kind


def _job(name: str, kind: str, shares: list[float], refused: str | None = None) -> JobResult:
    return JobResult(name, kind, name, [{"unexplained_share": x} for x in shares], refused=refused)


def test_the_share_bar_sits_between_the_user_fits_and_the_bad_input_it_must_refuse() -> None:
    """User fits leave at most 0.5 of the overpotential, the bad input at least 0.7 (its largest
    temperature): the bar is the middle, 0.6. A bad input the capacity rule refused first, with a
    share among the user fits', does not pull it down. Held out, a cell whose user fit sits above
    every other cell's is refused at the others' bar, and the summed row says so."""
    results = [_job("A_user", "user fit", [0.1, 0.2]), _job("B_user", "user fit", [0.5]),
               _job("A_ocv", "bad input", [0.4, 0.7]), _job("C_ocv", "bad input", [0.9]),
               _job("A_capacity", "bad input", [0.15], refused="x: --capacity-ah 2 is 15% more than the 1.7 Ah this "
                    "OCV test's slow branch moved at 25 °C"),
               _job("A_offset", "sensor offset", [0.2])]
    assert choose_share_bar(results) == pytest.approx(0.6)
    assert share_errors(results, 0.6) == (0, 0)
    assert share_errors(results, 0.45) == (1, 0) and share_errors(results, 0.8) == (0, 1)
    text = share_bar_table(results, 0.6)
    assert "| all but `B`, read on `B` | 0.45 | 1/1 | 0/0 |" in text
    assert "**1/2**" in text


def test_bars_that_tie_next_to_each_other_are_one_span() -> None:
    """A sensor-offset job at 0.5 (not counted) splits 0.2-0.7 into two spans of the same errors: the
    bar is the middle of the whole, 0.45, not of the wider piece (0.35)."""
    results = [_job("A_user", "user fit", [0.2]), _job("A_offset", "sensor offset", [0.5]),
               _job("A_ocv", "bad input", [0.7]), _job("C_ocv", "bad input", [0.9])]
    assert choose_share_bar(results) == pytest.approx(0.45)
