"""The hysteresis signature: the branch offset at the ends of long rests
(:func:`service.diagnosis.signatures.rest_branch_offset`), on HPPC-like recordings simulated
with the estimator's own model (:func:`research.validate.simulate_cell`)."""

from __future__ import annotations

import numpy as np
import pytest

from research import validate as va
from service.diagnosis.features import direction_state
from service.diagnosis.signatures import BRANCH_REST_MIN_S, rest_branch_offset


def hppc_current(rest_s: float = 1200.0) -> np.ndarray:
    """At ``validate.DT``: an opening rest, then 10 % of capacity at 1C, a long rest, a 10 s 2C
    discharge pulse, 40 s rest, a 10 s 1.5C charge pulse, 40 s rest; repeated 7 times."""
    def n(seconds: float) -> int:
        return round(seconds / va.DT)

    out = [0.0] * n(120)
    for _ in range(7):
        out += [va.CAP] * n(360) + [0.0] * n(rest_s)
        out += [2 * va.CAP] * n(12) + [0.0] * n(40) + [-1.5 * va.CAP] * n(12) + [0.0] * n(40)
    return np.array(out + [0.0] * n(600))


def branch(case: dict, seed: int = 0, rest_s: float = 1200.0) -> dict:
    cols, _ = va.simulate_cell(case, hppc_current(rest_s), seed)
    t, i, v, temp = cols.T
    return rest_branch_offset(t, i, v, temp, va.base_profile().ocv_table(), va.CAP)


@pytest.mark.parametrize("seed", [0, 1])
def test_hysteresis_is_measured_and_nominated(seed):
    half_gap = 0.012
    case = {"hysteresis": va.HysteresisSpec(u_h_max_v=half_gap, rate=30.0), "u_h0": -half_gap}
    b = branch(case, seed)
    assert b["nominated"], b
    assert b["n_rests"] >= 7  # the seven long rests (and the closing one)
    assert b["half_gap_v"] == pytest.approx(half_gap, rel=0.15)
    # one read stretch per rest, each inside a rest
    assert len(b["rest_tails"]) == b["n_rests"] and all(stop > start for start, stop in b["rest_tails"])


@pytest.mark.parametrize("effect", ["none", "capacity", "ocv", "kinetics"])
def test_no_nomination_without_hysteresis(effect):
    b = branch(va.CASES[effect]["clear"])
    assert not b["nominated"], b


def test_rests_above_the_table_after_discharge_are_not_a_hysteresis():
    """A constant +12 mV OCV error puts the post-discharge rests above the table: U_H < 0."""
    shift = va.OcvCorrectionSpec(soc=[0.0, 1.0], delta_v=[0.012, 0.012])
    b = branch({"extensions": va.Extensions(ocv_correction=shift)})
    assert b["half_gap_v"] == pytest.approx(-0.012, rel=0.15) and not b["nominated"]


def test_short_rests_give_no_signature():
    b = branch({"hysteresis": va.HysteresisSpec(u_h_max_v=0.012, rate=30.0)}, rest_s=BRANCH_REST_MIN_S / 2)
    assert b["n_rests"] < 4 and not b["nominated"] and "skipped" in b


def test_direction_state_follows_eq1():
    t = np.arange(0.0, 400.0, 1.0)
    i = np.where(t < 200, 2.0, -2.0)  # discharge then charge
    h = direction_state(t, i, 2.0, rate=100.0)
    assert h[0] == 0.0  # unknown history, and the first step has no duration
    # 199 s at 1C with rate 100: 1 - exp(-100 * 199 / 3600)
    assert h[199] == pytest.approx(-(1 - np.exp(-100 * 199 / 3600)), rel=1e-9)
    assert h[-1] > 0.9
    assert np.all(np.abs(h) <= 1.0)
