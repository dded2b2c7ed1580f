"""What searches that fit equally well can still disagree on: the polarisation under a sustained load."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.cell.profile import HysteresisSpec, ParameterPoint, load_profile
from service.characterisation.characterise import polarisation_spread_mv
from service.characterisation.sustained_load import SUSTAINED_C_RATE, sustained_polarisation_mv

PROFILE = Path(__file__).resolve().parents[1] / "service" / "assets" / "configs" / "cells" / "panasonic_18650pf.toml"


def _resistive_point(r_df: float) -> ParameterPoint:
    """Orders 1 and time constants of 1 s and 20 s: after ten minutes both branches are charged."""
    return ParameterPoint(temp_c=25.0, r_ohm=0.03, r_ct=0.01, c_dl=100.0, m=1.0, r_df=r_df, c_df=20.0 / r_df, n=1.0)


def test_a_settled_point_polarises_by_its_dc_resistance() -> None:
    """With every branch settled the polarisation is the 1C current times R_ohm + R_ct + R_df, and it
    grows by exactly the added R_df times the current."""
    template = load_profile(PROFILE)
    no_hysteresis = HysteresisSpec(u_h_max_v=0.0)
    current = SUSTAINED_C_RATE * template.effective_capacity_ah
    low = sustained_polarisation_mv(template, _resistive_point(0.02), no_hysteresis, memory_length=16)
    high = sustained_polarisation_mv(template, _resistive_point(0.06), no_hysteresis, memory_length=16)
    assert low == pytest.approx(1000 * current * 0.06, rel=0.03)
    assert high - low == pytest.approx(1000 * current * 0.04, rel=0.03)


def test_the_spread_counts_only_the_searches_that_fit_alike() -> None:
    # the second fits within the tolerance of the best (5 % + 0.5 mV); the third does not
    assert polarisation_spread_mv([20.0, 20.9, 30.0], [300.0, 250.0, 100.0]) == pytest.approx(50.0)
    assert polarisation_spread_mv([20.0, 22.0], [300.0, 100.0]) == 0.0
    assert polarisation_spread_mv([15.0], [80.0]) == 0.0
