"""The slow-relaxation measurement (``socd fit --slow-branch``) recovers a known slow branch."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.cell.profile import BranchSpec, CellProfile, Extensions
from service.cell.trajectory import simulate
from service.characterisation.characterise import FitReport, characterise
from service.characterisation.relaxation import long_rests, measure_slow_relaxation, rc_voltage
from service.recording import Recording
from tests.test_fitting import TRUE, nmc_like_ocv

#: the base branches as a drive-cycle fit finds them: diffusion τ = (R C)^(1/n) ≈ 1 min
BASE = TRUE.model_copy(update={"c_df": 1600.0})
SLOW = BranchSpec(r=0.016, c=3400.0 / 0.016, alpha=1.0)  # R 16 mΩ, τ 3400 s


def _lab_test(with_slow: bool, seed: int = 0, rest_s: float = 7200.0) -> Recording:
    """CALCE-like test of a 2 Ah cell: rest, 1 A discharge of 0.4 Ah, long rest, pulses, long rest.

    Sampled every 10 s in the rests and every 1 s under load (as the CALCE tester logs)."""
    rng = np.random.default_rng(seed)
    steps = [(600.0, 0.0, 10.0), (1440.0, 1.0, 1.0), (rest_s, 0.0, 10.0)]
    for _ in range(40):
        steps.append((float(rng.integers(20, 90)), float(rng.choice([2.0, 1.0, 0.5, -0.5])), 1.0))
    steps.append((rest_s, 0.0, 10.0))
    t, i, now = [0.0], [0.0], 0.0
    for dur, cur, dt in steps:
        for _ in range(int(dur / dt)):
            now += dt
            t.append(now)
            i.append(cur)
    t, i = np.array(t), np.array(i)
    ext = Extensions(extra_branches=[SLOW] if with_slow else [])
    prof = CellProfile(capacity_ah=2.0, ocv=nmc_like_ocv(), parameters=[BASE], extensions=ext)
    v, _ = simulate(prof, t, i, np.full(t.size, 25.0), 1.0)
    v = v + rng.normal(0.0, 0.2e-3, v.size)
    return Recording(Path(f"lab_{seed}.csv"), t, i, v, np.full(t.size, 25.0))


#: the fractional search's time bound where a test reads only what does not come from that search (the
#: OCV table, fitted jointly with the textbook 2-RC model, and the slow branch, measured from the rests)
SEARCH_S = 1.0


@pytest.fixture(scope="module")
def anchored_fit() -> tuple[Recording, CellProfile, FitReport]:
    """The lab test with a slow branch and its fit with the defaults (the rest anchor on): ``(rec, profile,
    report)``, shared by the tests that read it."""
    rec = _lab_test(True)
    prof, report = characterise([rec], 2.0, [None], max_seconds=SEARCH_S)
    return rec, prof, report


def test_rc_voltage_matches_the_step_recursion_on_uneven_steps():
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.5, 10.0, 5000))
    i = rng.normal(0.0, 1.0, t.size)
    for tau in (300.0, 3400.0, 1e5):
        d = np.exp(-np.diff(t, prepend=t[0]) / tau)
        x, ref = 0.0, np.empty(t.size)
        for k in range(t.size):
            x = d[k] * x + (1.0 - d[k]) * 0.02 * i[k]
            ref[k] = x
        assert np.max(np.abs(rc_voltage(t, i, 0.02, tau) - ref)) < 1e-12


def test_recovers_the_slow_branch_from_long_rests():
    rec = _lab_test(True)
    assert len(long_rests(rec, 2.0)) == 2  # the opening rest follows no load
    m = measure_slow_relaxation([rec], 2.0)
    assert m.r_ohm == pytest.approx(SLOW.r, rel=0.1)
    assert m.tau_s == pytest.approx(SLOW.r * SLOW.c, rel=0.1)
    assert m.rms_mv < 1.0


def test_a_cell_without_slow_relaxation_gets_a_negligible_branch():
    m = measure_slow_relaxation([_lab_test(False)], 2.0)
    # the base diffusion branch (τ about a minute) is over 5 minutes into a rest
    assert m.r_ohm < 0.1 * SLOW.r


def test_without_a_long_rest_fit_says_what_is_missing():
    rec = _lab_test(True, rest_s=600.0)
    with pytest.raises(ValueError, match=r"--slow-branch needs a rest of at least 30 min.*lab_0"):
        characterise([rec], 2.0, [None], slow_branch=True, max_seconds=2)


def test_profile_carries_the_measured_branch():
    prof, _ = characterise([_lab_test(True)], 2.0, [None], slow_branch=True, max_seconds=SEARCH_S)
    (branch,) = prof.extensions.extra_branches
    assert branch.r == pytest.approx(SLOW.r, rel=0.1)
    assert branch.r * branch.c == pytest.approx(SLOW.r * SLOW.c, rel=0.1)
    assert "slow_branch" in prof.notes
    assert prof.n_branches == 3


def _table_error_at_rests_mv(prof: CellProfile, rec: Recording, temp_c: float = 25.0) -> list[float]:
    """Fitted table at ``temp_c`` minus the voltage each long rest after the load relaxes towards
    (its relaxation limit, what ``--rest-anchor`` puts the table through)."""
    from service.characterisation.ocv_sources import rest_points

    table = prof.ocv_table()
    return [1000 * float(table.ocv(np.array([p.soc]), temp_c)[0] - p.ocv_v)
            for p in rest_points(rec, 2.0, 1.0, extrapolate=True)[1:]]


def test_rest_anchor_puts_the_joint_table_through_the_relaxed_rest_voltages(anchored_fit):
    """A cell with a slow branch, fitted without one: the rest anchor (the default) shifts the jointly
    fitted OCV onto the voltages the rests relaxed to, closer than the free joint fit passes them."""
    rec, anchored, report = anchored_fit
    free, free_report = characterise([rec], 2.0, [None], rest_anchor=False, max_seconds=SEARCH_S)
    # with --no-rest-anchor the log says how far the joint table sits from the rests
    (said,) = [line for line in free_report.lines if "relaxed voltage minus the joint OCV" in line]
    assert "3 rest(s)" in said and "--no-rest-anchor" in said
    err_free = _table_error_at_rests_mv(free, rec)
    err_anchored = _table_error_at_rests_mv(anchored, rec)
    assert len(err_anchored) == 2
    assert max(abs(e) for e in err_anchored) < 0.5, err_anchored
    assert max(abs(e) for e in err_anchored) < max(abs(e) for e in err_free), (err_anchored, err_free)
    assert any("anchored at the relaxed rest voltage" in line for line in report.lines)


def test_rest_anchor_anchors_every_temperature_at_its_own_rests():
    """Two temperatures, each with its own rests (the same test 15 mV lower at 10 °C): each row of
    the table goes through its own temperature's relaxed voltages, not the reference's."""
    warm = _lab_test(True)
    cold = Recording(Path("lab_cold.csv"), warm.time_s, warm.current_a, warm.voltage_v - 0.015,
                     np.full(warm.time_s.size, 10.0))
    prof, report = characterise([warm, cold], 2.0, [None, None], rest_anchor=True, max_seconds=SEARCH_S)
    for rec, temp in ((warm, 25.0), (cold, 10.0)):
        err = _table_error_at_rests_mv(prof, rec, temp)
        assert len(err) == 2 and max(abs(e) for e in err) < 0.5, (temp, err)
    assert sum("anchored at the relaxed rest voltage" in line for line in report.lines) == 2


def test_default_anchors_where_a_long_rest_exists_and_keeps_the_joint_table_where_none_does(anchored_fit):
    rec, default, _ = anchored_fit
    required, _ = characterise([rec], 2.0, [None], rest_anchor=True, max_seconds=SEARCH_S)
    assert default.ocv.ocv_v == required.ocv.ocv_v
    short = _lab_test(True, rest_s=300.0)
    short = short.slice(int(np.searchsorted(short.time_s, 600.0)))
    kept, report = characterise([short], 2.0, [None], max_seconds=SEARCH_S)
    free, _ = characterise([short], 2.0, [None], rest_anchor=False, max_seconds=SEARCH_S)
    assert kept.ocv.ocv_v == free.ocv.ocv_v
    assert any("no rest of 600 s or more to anchor" in line for line in report.lines)
    # an OCV table given: nothing to anchor, and no error without the flag
    table = (np.array(nmc_like_ocv().soc), np.array(nmc_like_ocv().ocv_v[0]))
    characterise([rec], 2.0, [None], ocv_table=table, max_seconds=SEARCH_S)


def test_rest_anchor_needs_a_jointly_fitted_table_and_a_long_rest():
    rec = _lab_test(True)
    with pytest.raises(ValueError, match="--rest-anchor"):
        characterise([rec], 2.0, [None], ocv_table=(np.array(nmc_like_ocv().soc), np.array(nmc_like_ocv().ocv_v[0])),
                     rest_anchor=True, max_seconds=2)
    with pytest.raises(ValueError, match="--rest-anchor: no rest of 600 s"):
        short = _lab_test(True, rest_s=300.0)
        characterise([short.slice(int(np.searchsorted(short.time_s, 600.0)))], 2.0, [None], rest_anchor=True,
                     max_seconds=2)


def test_relaxation_limit_extrapolates_a_first_order_decay_and_keeps_a_settled_rest():
    """A 20-min rest still relaxing (τ 10 min) ends 2.7 mV short of where it is going; the limit
    is recovered from the rest alone.  A settled rest, and a rest whose steps do not shrink, keep
    their end voltage."""
    from service.characterisation.ocv_sources import relaxation_limit

    t = np.arange(0.0, 1200.0, 1.0)
    relaxing = 3.7 - 0.02 * np.exp(-t / 600.0)
    assert 3.7 - relaxing[-1] > 2.5e-3
    assert relaxation_limit(t, relaxing) == pytest.approx(3.7, abs=0.2e-3)
    settled = 3.7 - 0.02 * np.exp(-t / 30.0)
    assert relaxation_limit(t, settled) == settled[-1]
    drifting = 3.7 + 1e-6 * t  # a straight line: equal steps, no decay to extrapolate
    assert relaxation_limit(t, drifting) == drifting[-1]


def test_a_small_cells_slow_branch_above_the_large_cell_bound_is_recovered():
    """On a 0.02 Ah cell a slow branch of 1.6 Ω (the 2 Ah lab test's 16 mΩ at 1/100 of the size) is
    above R_BOUNDS_OHM's 1 Ω, which a cell this small raises; the measurement recovers it."""
    from service.characterisation.relaxation import R_BOUNDS_OHM

    cap, r_s, tau_s = 0.02, 1.6, 3400.0
    assert r_s > R_BOUNDS_OHM[1]
    t = np.arange(0.0, 600.0 + 1440.0 + 7200.0, 5.0)
    i = np.where((t >= 600.0) & (t < 2040.0), 0.01, 0.0)  # a 0.5C discharge, then a two-hour rest
    v = 3.7 - rc_voltage(t, i, r_s, tau_s) + np.random.default_rng(0).normal(0.0, 0.2e-3, t.size)
    rec = Recording(Path("small.csv"), t, i, v, np.full(t.size, 25.0))
    slow = measure_slow_relaxation([rec], cap)
    assert slow.r_ohm == pytest.approx(r_s, rel=0.1)
    assert slow.tau_s == pytest.approx(tau_s, rel=0.15)
