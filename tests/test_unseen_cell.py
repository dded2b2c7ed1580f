"""research.unseen_cell: the PyBaMM cell it builds is what ``socd fit`` and the scoring expect (an
OCV test read as one, drives at the Panasonic C-rates with a coulomb-counted truth)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from research.validate_pybamm import I_NOISE_ABS, I_NOISE_REL
from service.cell.units import SECONDS_PER_HOUR
from service.characterisation.ocv_sources import is_ocv_test, slow_branches
from service.recording import load_recording

pytestmark = pytest.mark.research

CELL = "Marquis2019"  # the smallest and fastest set to simulate


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    pytest.importorskip("pybamm")
    import research.unseen_cell as uc

    if not (uc.PANASONIC / "pan18650pf_25C_US06.csv").is_file():
        pytest.skip(f"Panasonic recordings not found at {uc.PANASONIC}")
    workdir = tmp_path_factory.mktemp("unseen")
    mp = pytest.MonkeyPatch()
    mp.setattr(uc, "DRIVES", ("US06",))  # one drive and no pulse test keep the test short; the build is the same
    mp.setattr(uc, "PULSE_DRIVES", ())
    line = uc.build_cell(CELL, 25.0, workdir, seed=0)
    yield uc, workdir, line
    mp.undo()


def test_the_ocv_test_is_read_as_one_with_both_slow_branches(built):
    _, workdir, _ = built
    capacity = float(json.loads((workdir / f"{CELL}_25C_ocv.json").read_text())["capacity_ah"])
    rec = load_recording(workdir / f"{CELL}_25C_ocv.csv")
    assert is_ocv_test(rec, capacity)
    assert sorted(sign for sign, _ in slow_branches(rec, capacity)) == [-1.0, 1.0]
    # the capacity the user is told is the C/20 discharge's, and it spans the voltage window
    dt = np.diff(rec.time_s, prepend=rec.time_s[0])
    drawn = float(np.sum(np.clip(rec.current_a, 0.0, None) * dt)) / SECONDS_PER_HOUR
    assert drawn == pytest.approx(capacity, rel=0.02)


def test_the_drive_is_the_panasonic_current_at_the_same_c_rate_with_a_coulomb_truth(built):
    uc, workdir, _ = built
    capacity = float(json.loads((workdir / f"{CELL}_25C_ocv.json").read_text())["capacity_ah"])
    rec = load_recording(workdir / f"{CELL}_25C_US06.csv")
    pan = load_recording(uc.PANASONIC / "pan18650pf_25C_US06.csv")
    n = len(rec)
    assert n > 0.9 * len(pan), "the drive runs to the recording's end or the cut-off, not a few samples"
    expected = pan.current_a[:n] * capacity / uc.PANASONIC_AH
    noise = I_NOISE_REL * np.abs(expected) + I_NOISE_ABS
    assert np.mean(np.abs(rec.current_a - expected) / noise) < 1.5, "the current is the scaled one plus noise"
    assert rec.soc_true is not None and rec.soc_true[0] == pytest.approx(1.0)
    charge = np.concatenate([[0.0], np.cumsum(0.5 * (expected[1:] + expected[:-1]) * np.diff(rec.time_s))])
    counted = 1.0 - charge / (SECONDS_PER_HOUR * capacity)
    assert np.max(np.abs(rec.soc_true - counted)) < 0.005
    assert 3.0 < rec.voltage_v.min() and rec.voltage_v.max() < 4.3


def test_a_second_build_keeps_what_is_on_disk(built):
    uc, workdir, line = built
    stamps = {p.name: p.stat().st_mtime_ns for p in workdir.iterdir()}
    assert uc.build_cell(CELL, 25.0, workdir, seed=0) == line
    assert {p.name: p.stat().st_mtime_ns for p in workdir.iterdir()} == stamps


def test_the_ocv_test_read_on_the_discharge_scale_is_the_cells_own_ocv(built):
    """research.unseen_ocv_truth against PyBaMM's bulk OCV: the 25 °C C/20 charge stops short of full
    (found by the rest after it), and read with ``short_charge`` the test is within 4 mV of the
    cell's OCV below 90 % SOC."""
    _, workdir, _ = built
    from research.unseen_ocv_truth import BANDS, compare

    row = compare(CELL, 25.0, workdir)
    assert 0.95 < row.charge_reach < 1.0
    below_90 = [mv for (lo, hi), mv in zip(BANDS, row.short_charge_mv) if hi <= 0.9]
    assert below_90 and max(below_90) < 4.0


def test_an_ocv_test_the_solver_ran_past_the_cut_off_is_not_built(tmp_path, capsys):
    """PyBaMM's Ramadass2004 set at 10 °C steps over the C/20 discharge's stop at 2.8 V and runs on to
    tens of volts below zero: the build says so and writes nothing, where it wrote that as a recording.
    (Should a PyBaMM release stop it there, the build is kept and its voltages must stay above the cut-off.)"""
    pytest.importorskip("pybamm")
    import research.unseen_cell as uc

    mp = pytest.MonkeyPatch()
    mp.setattr(uc, "DRIVES", ())  # the OCV test alone: it comes first, and the drives use its capacity
    mp.setattr(uc, "PULSE_DRIVES", ())
    try:
        rc = uc.main(["build", "--cells", "Ramadass2004", "--ambients", "10", "--workdir", str(tmp_path)])
    finally:
        mp.undo()
    err = capsys.readouterr().err
    if rc == 0:
        rec = load_recording(tmp_path / "Ramadass2004_10C_ocv.csv")
        assert rec.voltage_v.min() > 2.8 - uc.CUT_OFF_OVERSHOOT_V
        return
    assert rc == 2
    assert "Ramadass2004_10C_ocv" in err and "past the 2.8 V lower cut-off" in err
    assert not list(tmp_path.iterdir())
