"""research.sigma_calibration: its score, its leave-one-cell-out choice and its command line."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from research.sigma_calibration import Score, crps_gaussian, main, parse_spec, report


def test_crps_matches_its_definition_by_quadrature() -> None:
    # CRPS = ∫ (F(y) - 1{y >= x})² dy for the Gaussian forecast F
    from scipy.integrate import trapezoid
    from scipy.stats import norm

    for err, sigma in ((0.3, 1.0), (-2.0, 0.5), (0.0, 0.01)):
        y = np.linspace(-20 * sigma - abs(err), 20 * sigma + abs(err), 200001)
        integrand = (norm.cdf(y, scale=sigma) - (y >= err)) ** 2
        assert crps_gaussian(np.array([err]), np.array([sigma]))[0] == pytest.approx(
            trapezoid(integrand, y), rel=1e-3)


def test_a_sigma_that_fits_the_errors_scores_better_than_one_too_narrow_or_too_wide() -> None:
    err = np.random.default_rng(0).normal(0.0, 1.0, 20000)
    scores = {s: float(np.mean(crps_gaussian(err, np.full_like(err, s)))) for s in (0.2, 1.0, 5.0)}
    assert scores[1.0] < scores[0.2] and scores[1.0] < scores[5.0]


def _score(cell: str, ocv: float, offset: float, crps: float) -> Score:
    return Score(cell, f"{cell}_rec", 0.0, ocv, offset, crps, 90.0, 1.0, 0.5)


def test_each_cell_is_scored_at_the_other_cells_choice() -> None:
    # cell a prefers (0.01, 0), cells b and c prefer (0.02, 0.01): a is held out at b and c's choice
    best = {"a": (0.01, 0.0), "b": (0.02, 0.01), "c": (0.02, 0.01)}
    scores = [_score(c, o, b, 0.1 if (o, b) == best[c] else 0.5)
              for c in best for o, b in ((0.01, 0.0), (0.02, 0.01), (0.0, 0.0))]
    lines, choice = report(scores)
    assert choice["held_out"]["a"] == [0.02, 0.01]
    assert choice["default"] == [0.02, 0.01]
    assert any(line.startswith("| a | 0.02 V, 0.01 C |") for line in lines)


def test_its_command_line_refuses_what_it_cannot_use(capsys) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="CELL=PROFILE:RECORDING"):
        parse_spec("no-cell-here.csv")
    assert parse_spec("a=p.toml:r.csv@120").full_at == "120"
    with pytest.raises(SystemExit) as exc:
        main(["a=p.toml:r.csv"])
    assert exc.value.code == 2 and "at least two cells" in capsys.readouterr().err
