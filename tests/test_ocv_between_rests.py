"""The OCV between a pulse test's rests (service/characterisation/ocv_sources.py): with no OCV test the
table is fitted jointly with the 2-RC model and anchored at the rests; between rests close in SOC it
can be read as the monotone cubic through them instead of the joint fit's shape."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.characterisation.ocv_choices import REST_INTERP_MAX_GAP
from service.characterisation.ocv_sources import (
    REST_MERGE_SOC,
    REST_SETTLED_V,
    RestPoint,
    interpolate_between_rests,
    merged_rests,
    rests_settled,
)
from service.cli import main

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "service" / "data" / "pan18650pf_25C_US06.csv"

GRID = np.linspace(0.0, 1.0, 201)


def true_ocv(soc: np.ndarray) -> np.ndarray:
    """A smooth NMC-like curve, V."""
    soc = np.asarray(soc, dtype=float)
    return 3.3 + 0.75 * soc + 0.12 * np.tanh((soc - 0.03) / 0.03) + 0.05 * soc ** 3


def rests_at(socs: list[float], unrelaxed_v: float = 0.0) -> list[RestPoint]:
    return [RestPoint(s, float(true_ocv(s)), 25.0, unrelaxed_v) for s in socs]


def wiggly_row() -> np.ndarray:
    """The true curve with a joint fit's wiggle between steps 10 % apart: ±15 mV, zero at the rests
    (monotone still, as a joint table is)."""
    return true_ocv(GRID) + 0.015 * np.sin(np.pi * GRID / 0.1)


def test_between_close_rests_the_row_follows_the_rests_not_the_wiggle() -> None:
    steps = [round(0.1 * k, 2) for k in range(1, 10)]
    row = interpolate_between_rests(GRID, wiggly_row(), rests_at(steps))
    inside = (GRID >= 0.1) & (GRID <= 0.9)
    assert np.max(np.abs(row - true_ocv(GRID))[inside]) < 2e-3
    assert np.max(np.abs(wiggly_row() - true_ocv(GRID))[inside]) > 0.014  # what it replaced
    assert np.all(np.diff(row) > 0)  # still a monotone table
    # beyond the rests: kept (make_monotone lifts each step by at most a µV)
    np.testing.assert_allclose(row[GRID < 0.09], wiggly_row()[GRID < 0.09], rtol=0, atol=1e-4)


def test_a_gap_wider_than_a_pulse_step_keeps_the_joint_shape() -> None:
    socs = [0.2, 0.3, 0.3 + REST_INTERP_MAX_GAP + 0.05, 0.7]
    row = interpolate_between_rests(GRID, wiggly_row(), rests_at(socs))
    gap = (GRID > 0.31) & (GRID < socs[2] - 0.01)
    np.testing.assert_allclose(row[gap], wiggly_row()[gap], rtol=0, atol=2e-4)
    close = (GRID > 0.21) & (GRID < 0.29)
    assert np.max(np.abs(row - true_ocv(GRID))[close]) < 2e-3


def test_rests_within_half_a_percent_are_one_reading() -> None:
    pts = [RestPoint(0.500, 3.70, 25.0), RestPoint(0.500 + 0.8 * REST_MERGE_SOC, 3.71, 25.0),
           RestPoint(0.60, 3.80, 25.0), RestPoint(1.5, 4.5, 25.0)]  # the last: not a usable SOC
    soc, ocv = merged_rests(pts)
    np.testing.assert_allclose(soc, [0.502, 0.60])
    np.testing.assert_allclose(ocv, [3.705, 3.80])
    # one reading: nothing to interpolate between
    np.testing.assert_array_equal(interpolate_between_rests(GRID, wiggly_row(), pts[:1]), wiggly_row())


def test_rests_have_settled_when_most_end_near_their_limit() -> None:
    assert rests_settled(rests_at([0.2, 0.5, 0.8], unrelaxed_v=0.3e-3))
    assert not rests_settled(rests_at([0.2, 0.5, 0.8], unrelaxed_v=2.5 * REST_SETTLED_V))
    mixed = rests_at([0.2, 0.5], unrelaxed_v=0.0) + rests_at([0.8], unrelaxed_v=0.01)
    assert rests_settled(mixed)  # the median decides: one cold tail does not
    assert not rests_settled([])


@pytest.mark.parametrize("value", ["spline", ""])
def test_fit_names_the_choices(value: str, capsys) -> None:
    assert main(["fit", "x.csv", "--capacity-ah", "2", "--ocv-between-rests", value, "-o", "y.toml"]) == 2
    err = capsys.readouterr().err
    assert "--ocv-between-rests" in err and "settled" in err and "joint" in err


def test_the_option_is_refused_where_there_is_no_joint_anchored_ocv(tmp_path: Path, capsys) -> None:
    out = tmp_path / "never.toml"
    argv = ["fit", str(BUNDLED), "--capacity-ah", "2.77", "--ocv-between-rests", "settled", "-o", str(out)]
    assert main([*argv, "--no-rest-anchor"]) == 2
    err = capsys.readouterr().err
    assert "--ocv-between-rests settled" in err and "--no-rest-anchor" in err
    assert not out.exists()


def test_near_reference_reads_through_the_rests_only_within_15_k_of_the_reference() -> None:
    from service.characterisation.characterise import reads_through_rests
    from service.characterisation.ocv_choices import NEAR_REFERENCE_K

    rests = rests_at([0.2, 0.5, 0.8])
    assert reads_through_rests("near-reference", 25.0, 25.0, rests)
    assert reads_through_rests("near-reference", 25.0 - NEAR_REFERENCE_K, 25.0, rests)
    assert not reads_through_rests("near-reference", 0.0, 25.0, rests)
    assert not reads_through_rests("near-reference", 45.0, 25.0, rests)
    assert reads_through_rests("interpolate", 0.0, 25.0, rests)
    assert not reads_through_rests("joint", 25.0, 25.0, rests)
    cold = rests_at([0.2, 0.5, 0.8], unrelaxed_v=2.5 * REST_SETTLED_V)
    assert reads_through_rests("settled", -20.0, 25.0, rests) and not reads_through_rests("settled", 25.0, 25.0, cold)


def test_by_default_the_rest_anchor_reads_through_the_rests_near_the_reference_only() -> None:
    """``socd fit``'s default (``ocv_between_rests=None``): the 25 °C row follows the rests, the 0 °C row
    keeps the joint fit's shape between them."""
    from service.characterisation.characterise import FitReport, anchor_rows_at_rests
    from service.characterisation.ocv_choices import DEFAULT_OCV_BETWEEN_RESTS

    steps = [round(0.1 * k, 2) for k in range(1, 10)]
    rows = {0.0: wiggly_row(), 25.0: wiggly_row()}
    anchor_rows_at_rests(FitReport(), GRID, rows, {0.0: rests_at(steps), 25.0: rests_at(steps)},
                         DEFAULT_OCV_BETWEEN_RESTS, 25.0)
    inside = (GRID >= 0.1) & (GRID <= 0.9)
    assert np.max(np.abs(rows[25.0] - true_ocv(GRID))[inside]) < 2e-3
    assert np.max(np.abs(rows[0.0] - true_ocv(GRID))[inside]) > 0.014


def test_the_fit_log_says_where_near_reference_keeps_the_joint_shape() -> None:
    from service.characterisation.characterise import FitReport, anchor_rows_at_rests

    steps = [round(0.1 * k, 2) for k in range(1, 10)]
    rep = FitReport()
    anchor_rows_at_rests(rep, GRID, {0.0: wiggly_row(), 25.0: wiggly_row()},
                         {0.0: rests_at(steps), 25.0: rests_at(steps)}, "near-reference", 25.0)
    said = "\n".join(rep.lines)
    assert "25 °C: between rests" in said and "monotone cubic through them" in said
    assert "0 °C: more than 15 K from the reference 25 °C" in said and "keeps the joint fit's shape" in said


def test_reference_shape_reads_the_cold_row_as_the_references_shifted_through_its_own_rests() -> None:
    """``reference-shape``: the 25 °C row follows its rests as near-reference's does; the 0 °C row is that
    row shifted through the 0 °C rests (here 30 mV below, with a joint row whose wiggle carries 15 mV of
    polarisation), not the joint fit's shape; and the log says so. Without a rest at the reference the
    cold row keeps the joint fit's shape, as near-reference's does."""
    from service.characterisation.characterise import (
        FitReport,
        anchor_rows_at_rests,
        reads_through_rests,
    )

    steps = [round(0.1 * k, 2) for k in range(1, 10)]
    cold = [RestPoint(p.soc, p.ocv_v - 0.030, 0.0, 0.005) for p in rests_at(steps)]
    rep = FitReport()
    rows = {0.0: wiggly_row() - 0.030, 25.0: wiggly_row()}
    anchor_rows_at_rests(rep, GRID, rows, {0.0: cold, 25.0: rests_at(steps)}, "reference-shape", 25.0)
    inside = (GRID >= 0.1) & (GRID <= 0.9)
    assert np.max(np.abs(rows[25.0] - true_ocv(GRID))[inside]) < 2e-3
    assert np.max(np.abs(rows[0.0] - (true_ocv(GRID) - 0.030))[inside]) < 2e-3
    assert "0 °C: more than 15 K from the reference 25 °C, so the OCV is the reference's row shifted" in "\n".join(rep.lines)
    assert reads_through_rests("reference-shape", 25.0, 25.0, cold) and not reads_through_rests("reference-shape", 0.0, 25.0, cold)
    rows = {0.0: wiggly_row() - 0.030, 25.0: wiggly_row()}
    anchor_rows_at_rests(FitReport(), GRID, rows, {0.0: cold, 25.0: []}, "reference-shape", 25.0)
    assert np.max(np.abs(rows[0.0] - (true_ocv(GRID) - 0.030))[inside]) > 0.014
