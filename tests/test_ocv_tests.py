"""``socd fit`` with slow OCV tests at several temperatures: each temperature's OCV comes from
its own test (or the tests either side of it), not from one average over every test."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.cell.profile import load_profile
from service.characterisation.ocv_sources import (
    ALIGN_SCALE_BOUNDS,
    OCV_BEYOND,
    RestPoint,
    is_ocv_test,
    ocv_from_test,
    ocv_row_from_rests,
    ocv_rows_by_temperature,
    slow_branches,
    soc_alignment,
)
from service.cli import build_parser, main
from service.recording import load_recording
from tests.conftest import NMC_CAPACITY_AH, nmc_ocv_points, write_recording_csv

#: the 0 °C test's OCV sits this far below the 25 °C one (an entropic shift, exaggerated)
COLD_SHIFT_V = -0.030


def write_ocv_test(path: Path, temp_c: float, shift_v: float, r_ohm: float = 0.05, charge_first: bool = False,
                   charge_to: float = 1.0, charge_logged: float = 1.0, current_noise_a: float = 0.0) -> Path:
    """A C/20 discharge from full to empty, an hour's rest, a C/20 charge back to full (60 s
    samples): the voltage is the synthetic cell's OCV plus ``shift_v`` minus the ohmic drop.
    ``charge_first``: the file starts half full with a 1C charge to full and a rest (a tester's
    OCV test usually does).  ``charge_to``: the charge stops at this SOC (a cold charge meets the
    voltage limit early); ``charge_logged``: the charge current is logged at this gain (the counts
    do not close, the cell still reaches full).  ``current_noise_a``: σ of the logged current's
    white noise (a current sensor's, seeded)."""
    soc_pts, ocv_pts = nmc_ocv_points()
    amps = NMC_CAPACITY_AH / 20.0
    n = 1200  # 20 h at 60 s
    i = np.concatenate([np.zeros(60), np.full(n, amps), np.zeros(60), np.full(round(n * charge_to), -amps), np.zeros(60)])
    start = 1.0
    if charge_first:
        i = np.concatenate([np.zeros(10), np.full(30, -NMC_CAPACITY_AH), i])  # 30 min at 1C from half full
        start = 0.5
    t = 60.0 * np.arange(i.size)
    soc = start - np.cumsum(i * 60.0) / 3600.0 / NMC_CAPACITY_AH
    v = np.interp(soc, soc_pts, ocv_pts) + shift_v - r_ohm * i
    logged = np.where(i < 0, charge_logged * i, i) + current_noise_a * np.random.default_rng(5).standard_normal(i.size)
    return write_recording_csv(path, t, logged, v, np.full(i.size, temp_c))


def test_an_ocv_test_gives_the_ocv_at_its_temperature(tmp_path: Path) -> None:
    rec = load_recording(write_ocv_test(tmp_path / "ocv0.csv", 0.0, COLD_SHIFT_V))
    curve = ocv_from_test(rec, NMC_CAPACITY_AH)
    grid, curve = curve.grid, curve.ocv_v
    soc_pts, ocv_pts = nmc_ocv_points()
    inside = (grid > 0.05) & (grid < 0.95)  # the ends of a sampled branch are coarse
    np.testing.assert_allclose(curve[inside], np.interp(grid, soc_pts, ocv_pts)[inside] + COLD_SHIFT_V, atol=2e-3)


def test_an_ocv_test_that_starts_with_a_fast_charge_is_still_one(tmp_path: Path, nmc_recording) -> None:
    """The slow branches make the test, not the file's peak current: a 1C charge before it is left out."""
    rec = load_recording(write_ocv_test(tmp_path / "ocv_cc.csv", 25.0, 0.0, charge_first=True))
    assert is_ocv_test(rec, NMC_CAPACITY_AH)
    curve = ocv_from_test(rec, NMC_CAPACITY_AH)
    grid, curve = curve.grid, curve.ocv_v
    soc_pts, ocv_pts = nmc_ocv_points()
    inside = (grid > 0.05) & (grid < 0.95)
    np.testing.assert_allclose(curve[inside], np.interp(grid, soc_pts, ocv_pts)[inside], atol=2e-3)
    # a drive cycle, and a C/20 discharge over only half the capacity, are not OCV tests
    drive = nmc_recording(name="drive", duration_s=3600, seed=2, soc0=0.95)
    assert not is_ocv_test(load_recording(drive.path), NMC_CAPACITY_AH)
    half = rec.slice(0, 40 + 60 + 600)
    assert not is_ocv_test(half, NMC_CAPACITY_AH)


def test_an_ocv_test_logged_with_a_noisy_current_sensor_is_still_one(tmp_path: Path) -> None:
    """A sensor whose noise is more than half the C/20 current (5 mA on a 0.17 Ah cell) puts single
    samples outside the C/100..C/10 band all along the branches; they must not cut them, and the
    curve read is the one a clean sensor gives, within what the noise does to the count itself (a
    random walk of about 2 % of SOC over each branch at 60 s samples, some 6 mV on this OCV)."""
    amps = NMC_CAPACITY_AH / 20.0
    rec = load_recording(write_ocv_test(tmp_path / "noisy.csv", 25.0, 0.0, current_noise_a=0.6 * amps))
    band = (rec.current_a > 0.01 * NMC_CAPACITY_AH) & (rec.current_a <= 0.1 * NMC_CAPACITY_AH)
    assert not band[60:1260].all()  # the raw samples do leave the band
    assert sorted(sign for sign, _ in slow_branches(rec, NMC_CAPACITY_AH)) == [-1.0, 1.0]
    clean = ocv_from_test(load_recording(write_ocv_test(tmp_path / "clean.csv", 25.0, 0.0)), NMC_CAPACITY_AH)
    noisy = ocv_from_test(rec, NMC_CAPACITY_AH)
    inside = (clean.grid > 0.05) & (clean.grid < 0.95)
    np.testing.assert_allclose(noisy.ocv_v[inside], clean.ocv_v[inside], atol=1e-2)


def test_a_charge_that_stopped_short_is_counted_on_the_discharge_scale(tmp_path: Path) -> None:
    """A charge that meets the voltage limit at 95 % rests below the voltage at full: with
    ``short_charge`` it is counted on the discharge's scale, not stretched over the whole range,
    and the top 5 % is the discharge branch raised to the rest at full; stretched (the default),
    the curve sits 20 mV low at 90 %."""
    rec = load_recording(write_ocv_test(tmp_path / "short.csv", 0.0, 0.0, charge_to=0.95))
    curve = ocv_from_test(rec, NMC_CAPACITY_AH, short_charge=True)
    assert curve.charge_reach == pytest.approx(0.95, abs=2e-3) and curve.short_charge
    soc_pts, ocv_pts = nmc_ocv_points()
    inside = (curve.grid > 0.05) & (curve.grid < 0.99)
    truth = np.interp(curve.grid, soc_pts, ocv_pts)
    np.testing.assert_allclose(curve.ocv_v[inside], truth[inside], atol=1.5e-3)
    # the default stretches it (the shortfall is still detected and reported)
    stretched = ocv_from_test(rec, NMC_CAPACITY_AH)
    assert stretched.charge_reach == curve.charge_reach and not stretched.short_charge
    assert np.interp(0.9, curve.grid, stretched.ocv_v - truth) < -0.01


def test_a_charge_whose_count_falls_short_but_reached_full_keeps_its_own_scale(tmp_path: Path) -> None:
    """The same shortfall in the count (charge current logged 5 % low) with the cell back at full:
    the rest after the charge matches the rest before the discharge, so even with ``short_charge``
    the charge is normalised by its own throughput."""
    rec = load_recording(write_ocv_test(tmp_path / "gain.csv", 0.0, 0.0, charge_logged=0.95))
    curve = ocv_from_test(rec, NMC_CAPACITY_AH, short_charge=True)
    assert curve.charge_reach == 1.0 and not curve.short_charge
    soc_pts, ocv_pts = nmc_ocv_points()
    inside = (curve.grid > 0.05) & (curve.grid < 0.95)
    np.testing.assert_allclose(curve.ocv_v[inside], np.interp(curve.grid, soc_pts, ocv_pts)[inside], atol=2e-3)


def test_rows_between_test_temperatures_are_interpolated_and_held_beyond() -> None:
    rows = ocv_rows_by_temperature({0.0: np.array([3.0, 3.5]), 20.0: np.array([3.2, 3.9])}, [-10.0, 5.0, 30.0])
    np.testing.assert_allclose(rows[-10.0], [3.0, 3.5])
    np.testing.assert_allclose(rows[5.0], [3.05, 3.6])
    np.testing.assert_allclose(rows[30.0], [3.2, 3.9])


def test_rows_beyond_the_tests_carry_their_slope_on_when_asked() -> None:
    """``linear``: beyond the tests, the line through the two nearest (kept monotone in SOC); one
    test is held either way; an unknown rule is refused."""
    tests = {0.0: np.array([3.0, 3.5]), 10.0: np.array([3.1, 3.6]), 20.0: np.array([3.2, 3.9])}
    rows = ocv_rows_by_temperature(tests, [-10.0, 5.0, 30.0], beyond="linear")
    np.testing.assert_allclose(rows[-10.0], [2.9, 3.4], atol=1e-5)
    np.testing.assert_allclose(rows[5.0], [3.05, 3.55])
    np.testing.assert_allclose(rows[30.0], [3.3, 4.2], atol=1e-5)
    crossing = ocv_rows_by_temperature({0.0: np.array([3.0, 3.1]), 10.0: np.array([3.2, 3.15])}, [40.0], "linear")
    assert np.all(np.diff(crossing[40.0]) >= 0.0)
    np.testing.assert_allclose(ocv_rows_by_temperature({25.0: np.array([3.0, 3.5])}, [40.0], "linear")[40.0], [3.0, 3.5])
    with pytest.raises(ValueError, match="quadratic"):
        ocv_rows_by_temperature(tests, [40.0], "quadratic")


def test_fit_offers_every_rule_beyond_the_tests_and_no_other() -> None:
    """``socd fit --ocv-beyond`` spells its choices out (the CLI does not import the fit's numerics
    to start); they are :data:`OCV_BEYOND`, with ``hold`` the default."""
    fit = build_parser()._subparsers._group_actions[0].choices["fit"]
    action = next(a for a in fit._actions if a.dest == "ocv_beyond")
    assert tuple(action.choices) == OCV_BEYOND and action.default == OCV_BEYOND[0]


def test_fit_keeps_each_ocv_test_at_its_own_temperature(tmp_path: Path, nmc_recording, capsys) -> None:
    """OCV tests at 0 and 25 °C and a drive at each: the profile's 0 °C row is the 0 °C test's
    curve and its 25 °C row the 25 °C test's; averaging the two would put both 15 mV off."""
    tests = [write_ocv_test(tmp_path / "ocv25.csv", 25.0, 0.0), write_ocv_test(tmp_path / "ocv0.csv", 0.0, COLD_SHIFT_V)]
    drives = [nmc_recording(name=f"drive{t:g}", duration_s=1800, seed=5, soc0=0.95, temp_c=t) for t in (25.0, 0.0)]
    out = tmp_path / "cell.toml"
    rc = main(["fit", "--candidates", "1", *map(str, tests), *(str(d.path) for d in drives), "--capacity-ah", str(NMC_CAPACITY_AH),
               "--max-seconds", "5", "--force", "-q", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    table = load_profile(out).ocv_table()
    soc_pts, ocv_pts = nmc_ocv_points()
    mid = np.linspace(0.1, 0.9, 17)
    for temp_c, shift in ((25.0, 0.0), (0.0, COLD_SHIFT_V)):
        got = table.ocv(mid, np.full(mid.size, temp_c))
        np.testing.assert_allclose(got, np.interp(mid, soc_pts, ocv_pts) + shift, atol=3e-3)


def _panasonic_like_curve() -> tuple[np.ndarray, np.ndarray]:
    """An OCV test's curve on the 201-point grid: steep below 10 % SOC, as a real NMC cell's is."""
    soc = np.linspace(0.0, 1.0, 201)
    return soc, 3.45 + 0.7 * (soc - 0.2) - 0.45 * np.exp(-soc / 0.04)


def test_rests_counted_on_another_scale_align_the_curve_instead_of_bending_it_flat() -> None:
    """An HPPC test counts SOC with the profile's capacity from its own full point; its cell holds
    3 % less charge than the OCV test's throughput says. The rest voltages then sit on the test curve
    at SOC_test = 1 + 0.97 (SOC_counted - 1), which near empty is far up the steep part: as a voltage
    offset that is 0.4 V, and the running max after it makes the row flat over the lowest 10 %."""
    soc, curve = _panasonic_like_curve()
    counted = np.concatenate([np.linspace(1.0, 0.1, 19), [0.05, 0.005]])
    rests = [RestPoint(float(s), float(np.interp(1.0 + 0.97 * (s - 1.0), soc, curve)) - 0.005, 25.0) for s in counted]
    shift, scale = soc_alignment(soc, curve, counted, np.array([p.ocv_v for p in rests]))
    assert abs(shift) < 2e-3 and abs(scale - 0.97) < 2e-3
    row = ocv_row_from_rests(soc, curve, rests)
    assert np.all(np.diff(row) > 1e-4)  # no flat stretch: SOC stays observable near empty
    truth = np.interp(1.0 + 0.97 * (soc - 1.0), soc, curve) - 0.005
    low = soc <= 0.1
    assert np.max(np.abs(row - truth)[low]) < 2e-3
    assert np.max(np.abs(row - truth)) < 2e-3


def test_rests_over_a_narrow_span_only_shift_the_curve() -> None:
    """Three rests within 0.2 SOC cannot fix a scale: the curve is shifted by their offset as before."""
    soc, curve = _panasonic_like_curve()
    rests = [RestPoint(s, float(np.interp(s, soc, curve)) + 0.01, 25.0) for s in (0.5, 0.6, 0.7)]
    np.testing.assert_allclose(ocv_row_from_rests(soc, curve, rests), curve + 0.01 + 1e-6 * np.arange(soc.size), atol=1e-9)


def test_fit_reports_the_alignment_and_flags_one_at_its_bound() -> None:
    """The fit log says what capacity the OCV curve's SOC implies between the rests; rests counted
    with a capacity 20 % off (a wrong --capacity-ah) end on the alignment's bound and get a notice."""
    from service.characterisation.characterise import FitReport, say_rest_alignment

    soc, curve = _panasonic_like_curve()
    counted = np.linspace(1.0, 0.1, 19)
    for true_scale, flagged in ((0.97, False), (0.8, True)):
        rests = [RestPoint(float(s), float(np.interp(1.0 + true_scale * (s - 1.0), soc, curve)), 25.0) for s in counted]
        rep = FitReport(echo=lambda line: None)
        say_rest_alignment(rep, 25.0, soc, curve, rests, capacity_ah=2.0)
        held_at = max(true_scale, ALIGN_SCALE_BOUNDS[0])  # the bound holds a scale beyond it
        assert f"{2.0 / held_at:.3f} Ah" in rep.lines[0]
        assert any("at its bound" in line for line in rep.lines) == flagged


def test_fit_refuses_a_capacity_above_what_its_ocv_test_moved(tmp_path: Path, nmc_recording, capsys) -> None:
    """The OCV test's C/20 discharge took out the cell's capacity; told 15 % more, every SOC the
    profile counts would drift by that, and no fit RMSE shows it. The command names the test and the
    charge it measured, exits 2 and writes nothing; --force fits it, saying so. 3 % more (a tester's
    count, a charge just short of full) is fitted with a notice, 3 % less without a word."""
    test = write_ocv_test(tmp_path / "ocv25.csv", 25.0, 0.0)
    drive = nmc_recording(name="drive", duration_s=1800, seed=5, soc0=0.95)
    out = tmp_path / "cell.toml"
    fit = ["fit", "--candidates", "1", str(test), str(drive.path), "--max-seconds", "3", "-q", "-o", str(out)]
    assert main([*fit, "--capacity-ah", f"{1.15 * NMC_CAPACITY_AH:g}"]) == 2
    err = capsys.readouterr().err
    assert "ocv25.csv: --capacity-ah" in err and "15.0% more than the" in err and f"{NMC_CAPACITY_AH:.4g} Ah" in err
    assert "Traceback" not in err and not out.exists()
    assert main([*fit, "--capacity-ah", f"{1.15 * NMC_CAPACITY_AH:g}", "--force"]) == 0 and out.exists()
    assert "--force fits with --capacity-ah" in capsys.readouterr().err  # said, even with -q
    out.unlink()
    assert main([*fit, "--capacity-ah", f"{1.03 * NMC_CAPACITY_AH:g}"]) == 0
    err = capsys.readouterr().err  # each percent costs SOC: said, even with -q
    assert "notice: " in err and "ocv25.csv: --capacity-ah" in err and "3.0% more" in err
    assert main([*fit, "--capacity-ah", f"{0.97 * NMC_CAPACITY_AH:g}"]) == 0
    assert "OCV test's slow branch" not in capsys.readouterr().err  # less than C/20 gave is what drives give
