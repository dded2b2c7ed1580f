"""``research.fit_quality`` reads what ``socd fit`` says about each temperature, and judges it by
the product's own rule (the table in docs/results/characterisation.md rests on this)."""

from __future__ import annotations

from pathlib import Path

import pytest

from research.fit_quality import read_fit_log, refusal_kind
from service.cli import main
from tests.conftest import NMC_CAPACITY_AH


def test_the_fit_log_gives_each_temperatures_figures_and_the_products_verdict(tmp_path: Path, nmc_recording,
                                                                             nmc_ocv_csv: Path, capsys) -> None:
    drive = nmc_recording(name="drive", duration_s=1800, seed=5, soc0=0.95)
    out = tmp_path / "cell.toml"
    assert main(["fit", str(drive.path), "--ocv", str(nmc_ocv_csv), "--capacity-ah", str(NMC_CAPACITY_AH),
                 "--max-seconds", "3", "--force", "-o", str(out)]) == 0
    rows = read_fit_log(capsys.readouterr().err)
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
