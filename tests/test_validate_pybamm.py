"""The PyBaMM stand-in for the blind set: its drives and its table (PyBaMM itself is optional)."""

from __future__ import annotations

import numpy as np
import pytest

from research.validate_pybamm import Row, drive, table

pytestmark = pytest.mark.research


@pytest.mark.parametrize("kind", ["dst", "walk"])
def test_drive_opens_and_ends_with_rests_and_draws_three_quarters(kind):
    i = drive(kind, 3, 5.0)
    assert np.all(i[:60] == 0.0) and np.all(i[-600:] == 0.0)
    drawn = i.sum() / 3600.0
    assert 0.75 * 5.0 <= drawn < 0.75 * 5.0 + 3.0 * 5.0 * 90 / 3600  # overshoot at most one step
    assert (i < 0).any(), "regen / charging present"
    assert not np.array_equal(drive(kind, 4, 5.0)[:2000], i[:2000]), "the seed changes the drive"


def test_smooth_drive_is_like_the_labelled_randomwalk():
    """The smooth drive stands in for the labelled ``randomwalk`` files: a correlated current with
    a quarter or so of the time charging, few long rests and no regen while the first 10 % is drawn."""
    for seed in (1, 2, 3):
        i = drive("smooth", seed, 5.0) / 5.0
        assert np.all(i[:60] == 0.0) and np.all(i[-600:] == 0.0)
        load = i[60:-600]
        assert 0.2 <= load.mean() <= 0.5 and 0.4 <= load.std() <= 0.9
        assert 0.1 <= np.mean(load < -0.03) <= 0.35
        assert load.min() >= -1.6 and load.max() <= 2.7
        x = load - load.mean()
        assert np.corrcoef(x[:-20], x[20:])[0, 1] > 0.4, "correlated over tens of seconds"
        rest = np.abs(load) < 0.01
        starts = np.flatnonzero(np.diff(rest.astype(int)) == 1)
        lengths = [int(np.argmin(rest[s + 1:])) for s in starts]
        assert 2 <= sum(n >= 240 for n in lengths) <= 3, "two or three rests of 4-8 min"
        first = np.cumsum(load) < 0.1 * 3600.0
        assert np.all(load[: int(np.argmin(first))] >= 0.0), "no regen near full"


def _row(cell, effect, verdict):
    return Row(effect=effect, level="moderate", seed=1, verdict=verdict, state="named", top=verdict, top_score=0.5,
               seconds=1.0, stem=f"{cell}_{effect}", cell=cell, rmse_before_mv=10.0, rmse_after_mv=5.0)


def test_table_counts_right_wrong_and_false_positives():
    rows = [_row("A", "none", "none"), _row("A", "none", "kinetics"), _row("A", "capacity", "capacity"),
            _row("B", "none", "none"), _row("B", "hysteresis", "none"), _row("B", "diffusion", "kinetics")]
    text = table(rows)
    assert "| A | 1/2 (kinetics) |" in text
    assert "| B | 1/1 |" in text and "0/1 (kinetics)" in text
    assert "named right: 3/6; clean named as an effect: 1/3; effects named as another effect: 1/3" in text


def test_signature_table_counts_each_signature_and_lists_failed_simulations():
    from research.validate_pybamm import signature_table

    def row(effect, hyst, diff, kin=False, n_rests=5):
        return {"stem": f"A_{effect}", "cell": "A", "effect": effect, "nominated": hyst, "n_rests": n_rests,
                "half_gap_v": 0.01, "statistic": 9.0, "spread": 0.05, "relaxation": 0.2,
                "diffusion": {"nominated": diff, "n_rests": 4, "statistic": 0.5 if diff else 0.1, "z": 20.0},
                "kinetics": {"nominated": kin, "n_steps": 40, "i0_c": 0.05 if kin else 0.3, "i0_upper_c": 0.06 if kin else 0.35}}

    rows = [row("hysteresis", True, False), row("diffusion", False, True), row("diffusion", False, False),
            row("none", False, False), row("kinetics", False, False, kin=True),
            {"stem": "B_capacity", "cell": "B", "effect": "capacity", "error": "SolverError: x"}]
    text = signature_table(rows)
    assert "hysteresis signature: nominated on 1/1 hysteresis recordings and on 0/4 others" in text
    assert "diffusion signature: nominated on 1/2 diffusion recordings and on 0/3 others" in text
    assert "kinetics signature: nominated on 1/1 kinetics recordings and on 0/4 others" in text
    assert "| 40 | 0.050 (0.060) | **yes** |" in text
    assert "not simulated: B_capacity (SolverError: x)" in text


def test_run_one_returns_a_failed_row_instead_of_ending_the_run(monkeypatch, tmp_path):
    """A recording the solver cannot run comes back as a row with its error, and the table lists it.
    PyBaMM is optional (not in CI), so its solver failure is stood in by the drawn-charge check's
    RuntimeError and a stand-in module for ``SolverError``."""
    import types

    import research.validate_pybamm as vp

    def failing(cell, effect, level, seed, kind):
        raise RuntimeError(f"{cell} {effect}: solver drew 1.000 Ah, the drive 3.000 Ah")

    monkeypatch.setattr(vp, "simulate", failing)
    monkeypatch.setattr(vp, "_pybamm", lambda: types.SimpleNamespace(SolverError=ArithmeticError))
    row = vp.run_one(("Ai2020", "capacity", "clear", 401, "dst", str(tmp_path)))
    assert row == {"stem": "Ai2020_capacity_clear_dst_s401", "cell": "Ai2020", "effect": "capacity",
                   "error": "RuntimeError: Ai2020 capacity: solver drew 1.000 Ah, the drive 3.000 Ah"}
    assert not list(tmp_path.iterdir()), "nothing written for a recording that was not simulated"
    text = table([_row("A", "none", "none")], [row])
    assert "named right: 1/1" in text
    assert "not simulated: Ai2020_capacity_clear_dst_s401 (RuntimeError: Ai2020 capacity" in text


def test_hysteresis_state_follows_the_charge_moved_whatever_the_sampling():
    """Zeng Eq. 1 with U_H = 1: rest holds the state, a discharge drives it towards −1 by 1 − e⁻¹ of
    the way per 1/rate of the capacity moved, and one 60 s sample moves it as sixty 1 s samples do."""
    from research.validate_pybamm import HYSTERESIS_RATE, hysteresis_state

    cap = 2.0
    rest = hysteresis_state(np.arange(100.0), np.zeros(100), cap, start=1.0)
    assert np.all(rest == 1.0)
    # discharge 1/rate of the capacity at 1C: 3600 / rate seconds
    n = round(3600.0 / HYSTERESIS_RATE)
    h = hysteresis_state(np.arange(n + 1.0), np.r_[0.0, np.full(n, cap)], cap, start=1.0)
    assert h[-1] == pytest.approx(1.0 - 2.0 * (1.0 - np.exp(-1.0)), abs=1e-9)
    fine = hysteresis_state(np.arange(61.0), np.r_[0.0, np.full(60, -0.5)], cap, start=-1.0)
    coarse = hysteresis_state(np.array([0.0, 60.0]), np.array([0.0, -0.5]), cap, start=-1.0)
    assert coarse[-1] == pytest.approx(fine[-1], rel=1e-12) and fine[-1] > -1.0
