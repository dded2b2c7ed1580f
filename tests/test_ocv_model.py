"""OCV table, hysteresis, coulomb counting, the batched MTS-FOM and cell profile files."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from service.assets import profile_path
from service.cell.coulomb import coulomb_soc
from service.cell.hysteresis import hysteresis_decay, hysteresis_step
from service.cell.model import MtsFom, soc_step
from service.cell.ocv import GRID_POINTS, OcvTable, make_monotone
from service.cell.profile import (
    ArrheniusSpec,
    BranchSpec,
    CellProfile,
    Extensions,
    HysteresisSpec,
    OcvCorrectionSpec,
    ProfileError,
    load_profile,
    save_profile,
)
from service.cell.trajectory import simulate

# make_monotone adds 1e-6 V per grid step so rows are strictly increasing
MONOTONE_NUDGE_V = 1e-6 * GRID_POINTS


# -- OCV ----------------------------------------------------------------------------------
def test_lookup_reproduces_table_points(nmc_profile: CellProfile) -> None:
    soc = np.array(nmc_profile.ocv.soc)
    ocv = np.array(nmc_profile.ocv.ocv_v[0])
    table = nmc_profile.ocv_table()
    np.testing.assert_allclose(table.ocv(soc), ocv, atol=MONOTONE_NUDGE_V)
    assert table.ocv(0.5).shape == ()
    assert table.ocv(np.full((3, 4), 0.5)).shape == (3, 4)


def test_linear_table_lookup_slope_and_extrapolation() -> None:
    table = OcvTable.from_points(np.array([0.0, 1.0]), np.array([3.0, 4.0]))
    s = np.linspace(-0.08, 1.08, 59)
    slope = 1.0 + 1e-6 * (GRID_POINTS - 1)
    np.testing.assert_allclose(table.ocv(s), 3.0 + slope * s, atol=1e-12)
    np.testing.assert_allclose(table.slope(s), slope, rtol=1e-9)


def test_slope_matches_finite_difference(nmc_profile: CellProfile) -> None:
    table = nmc_profile.ocv_table()
    # midpoints of grid cells: the slope there is the cell's secant
    mid = (np.arange(GRID_POINTS - 1) + 0.5) / (GRID_POINTS - 1)
    h = 1e-4
    fd = (table.ocv(mid + h) - table.ocv(mid - h)) / (2 * h)
    np.testing.assert_allclose(table.slope(mid), fd, rtol=1e-6)
    assert np.all(table.slope(mid) > 0)


def test_inverse_round_trip(nmc_profile: CellProfile) -> None:
    table = nmc_profile.ocv_table()
    s = np.linspace(0.0, 1.0, 777)
    np.testing.assert_allclose(table.soc_from_ocv(table.ocv(s)), s, atol=1e-9)
    v = np.linspace(table.ocv(0.0), table.ocv(1.0), 50)
    np.testing.assert_allclose(table.ocv(table.soc_from_ocv(v)), v, atol=1e-9)
    # outside the table the inverse saturates to [0, 1]
    np.testing.assert_array_equal(table.soc_from_ocv(np.array([1.0, 9.0])), [0.0, 1.0])


def test_monotone_enforcement() -> None:
    soc = np.linspace(0.0, 1.0, 11)
    ocv = 3.5 + 0.6 * soc
    ocv[5] -= 0.1  # a dip, as a noisy measured table would have
    ocv[6] -= 0.05
    table = OcvTable.from_points(soc, ocv)
    assert np.all(np.diff(table.ocv_v[0]) > 0)
    # the smallest upward correction: the running maximum (plus the nudge)
    row = np.array([3.0, 3.2, 3.1, 3.15, 3.4])
    np.testing.assert_allclose(make_monotone(row), [3.0, 3.2, 3.2, 3.2, 3.4] + 1e-6 * np.arange(5))
    # the inverse is single-valued
    grid = table.soc_grid
    np.testing.assert_allclose(table.soc_from_ocv(table.ocv(grid)), grid, atol=1e-9)


def test_temperature_interpolation_and_hold() -> None:
    soc = np.linspace(0.0, 1.0, 5)
    rows = np.array([3.4 + 0.8 * soc, 3.5 + 0.8 * soc])  # given 40 °C first: must be sorted
    table = OcvTable.from_points(soc, rows, np.array([40.0, 0.0]))
    np.testing.assert_array_equal(table.temps_c, [0.0, 40.0])
    s = np.array([0.2, 0.5, 0.9])
    v0 = table.ocv(s, 0.0)
    v40 = table.ocv(s, 40.0)
    np.testing.assert_allclose(v40 - v0, -0.1, atol=1e-12)  # 40 °C row is 3.4 + ...
    np.testing.assert_allclose(table.ocv(s, 10.0), v0 + 0.25 * (v40 - v0), atol=1e-12)
    np.testing.assert_allclose(table.ocv(s, -20.0), v0, atol=1e-12)  # held outside
    np.testing.assert_allclose(table.ocv(s, 60.0), v40, atol=1e-12)
    # per-cell temperatures broadcast against SOC
    np.testing.assert_allclose(table.ocv(0.5, np.array([0.0, 20.0, 40.0])),
                               [table.ocv(0.5, 0.0), table.ocv(0.5, 20.0), table.ocv(0.5, 40.0)])
    np.testing.assert_allclose(table.soc_from_ocv(table.ocv(s, 20.0), 20.0), s, atol=1e-9)


def test_table_shape_errors() -> None:
    with pytest.raises(ValueError, match="does not match"):
        OcvTable.from_points(np.linspace(0, 1, 5), np.ones((2, 5)), np.array([25.0]))
    with pytest.raises(ValueError, match="strictly increasing"):
        OcvTable.from_points(np.array([0.0, 0.5, 0.5, 1.0]), np.array([3.0, 3.5, 3.6, 4.0]))
    with pytest.raises(ValueError, match="non-finite"):
        OcvTable.from_points(np.array([0.0, 1.0]), np.array([3.0, np.nan]))


# -- hysteresis -----------------------------------------------------------------------------
def test_hysteresis_sign_convention() -> None:
    u_max, rate, q = np.array([0.03]), np.array([30.0]), np.array([2.0])
    charge = discharge = rest = np.array([0.01])
    for _ in range(3000):
        charge = hysteresis_step(charge, np.array([-2.0]), 1.0, u_max, rate, q)
        discharge = hysteresis_step(discharge, np.array([2.0]), 1.0, u_max, rate, q)
        rest = hysteresis_step(rest, np.array([0.0]), 1.0, u_max, rate, q)
    assert charge[0] == pytest.approx(0.03, abs=1e-6)  # charge (I < 0) → +U_H
    assert discharge[0] == pytest.approx(-0.03, abs=1e-6)  # discharge (I > 0) → −U_H
    assert rest[0] == 0.01  # at rest U_h holds


def test_hysteresis_decay_formula() -> None:
    a = hysteresis_decay(np.array([1.5, -1.5]), 2.0, np.array([30.0, 30.0]), np.array([2.0, 2.0]))
    np.testing.assert_allclose(a, np.exp(-30.0 * 1.5 * 2.0 / (3600.0 * 2.0)))
    u = hysteresis_step(np.array([0.0]), np.array([1.5]), 2.0, np.array([0.02]), np.array([30.0]), np.array([2.0]))
    assert u[0] == pytest.approx(-(1.0 - a[0]) * 0.02)


def test_hysteresis_in_the_model_raises_voltage_after_charge(nmc_profile_factory) -> None:
    prof = nmc_profile_factory(hysteresis=HysteresisSpec(u_h_max_v=0.02, rate=200.0))
    n = 2400
    t = np.arange(n, dtype=float)
    i = np.concatenate([np.full(1200, -2.0), np.zeros(1200)])  # long charge, long rest
    v, soc = simulate(prof, t, i, np.full(n, 25.0), 0.4)
    ocv = prof.ocv_table().ocv(soc[-1])
    assert v[-1] - ocv == pytest.approx(0.02, abs=2e-3)


# -- SOC -------------------------------------------------------------------------------------
def test_soc_step_uses_actual_interval() -> None:
    s = soc_step(np.array([0.8, 0.8]), np.array([2.0, -1.0]), 36.0, np.array([2.0, 2.0]))
    np.testing.assert_allclose(s, [0.8 - 0.01, 0.8 + 0.005])


def test_model_soc_is_coulomb_count_with_actual_dt(nmc_profile: CellProfile) -> None:
    rng = np.random.default_rng(3)
    n = 400
    t = np.cumsum(rng.choice([0.5, 1.0, 1.0, 2.0, 10.0], n))
    i = rng.normal(0.5, 2.0, n)
    _, soc = simulate(nmc_profile, t, i, np.full(n, 25.0), 0.7)
    # backward zero-order hold: row k's current flowed over (t_{k-1}, t_k]
    expected = 0.7 - np.cumsum(i * np.diff(t, prepend=t[0])) / (3600.0 * nmc_profile.capacity_ah)
    np.testing.assert_allclose(soc, expected, atol=1e-12)
    np.testing.assert_allclose(coulomb_soc(t, i, nmc_profile.capacity_ah, 0.7), expected, atol=1e-12)


def test_model_soc_applies_bias_and_capacity_scale(nmc_profile_factory) -> None:
    prof = nmc_profile_factory(extensions=Extensions(current_bias_a=0.1, capacity_scale=0.8))
    n = 100
    t = np.arange(n, dtype=float) * 3.0
    i = np.full(n, 1.0)
    _, soc = simulate(prof, t, i, np.full(n, 25.0), 0.9)
    assert soc[-1] == pytest.approx(0.9 - 0.9 * (n - 1) * 3.0 / (3600.0 * 1.6), rel=1e-12)


# -- the batched model -----------------------------------------------------------------------
def test_batch_of_cells_equals_single_runs(nmc_profile_factory) -> None:
    prof = nmc_profile_factory(
        hysteresis=HysteresisSpec(u_h_max_v=0.015, rate=50.0),
        extensions=Extensions(extra_branches=[BranchSpec(r=0.005, c=20000.0, alpha=0.9)]),
    )
    N, T = 6, 250
    rng = np.random.default_rng(11)
    params = prof.parameters_at(np.linspace(15.0, 35.0, N))
    params.r_ohm = params.r_ohm * rng.uniform(0.7, 1.3, N)
    params.r = params.r * rng.uniform(0.7, 1.3, params.r.shape)
    params.alpha = np.clip(params.alpha * rng.uniform(0.8, 1.1, params.alpha.shape), 0.3, 1.0)
    assert params.r.shape == (N, 3)
    soc0 = rng.uniform(0.2, 0.9, N)
    u_h0 = rng.uniform(-0.01, 0.01, N)
    temp = np.linspace(15.0, 35.0, N)
    current = rng.normal(0.0, 3.0, (T, N))
    dt = rng.choice([0.5, 1.0, 2.0], T)

    batch = MtsFom(prof, params, soc0, memory_length=24, u_h0=u_h0)
    v_batch = np.array([batch.step(dt[k], current[k], temp) for k in range(T)])
    for c in range(N):
        one = MtsFom(prof, params.take(slice(c, c + 1)), soc0[c : c + 1], memory_length=24, u_h0=u_h0[c : c + 1])
        v_one = np.array([one.step(dt[k], current[k, c : c + 1], temp[c : c + 1])[0] for k in range(T)])
        np.testing.assert_allclose(v_batch[:, c], v_one, rtol=0, atol=1e-12)
        assert batch.soc[c] == pytest.approx(one.soc[0], abs=1e-14)
        np.testing.assert_allclose(batch.history[c], one.history[0], atol=1e-14)


def test_simulate_candidates_equal_single_simulations(nmc_profile: CellProfile) -> None:
    n = 300
    t = np.arange(n, dtype=float)
    i = np.where((t // 50) % 2 == 0, 3.0, -1.0)
    temp = np.full(n, 25.0)
    params = nmc_profile.parameters_at(25.0, n_cells=3)
    params.r_ohm = params.r_ohm * np.array([0.5, 1.0, 2.0])
    v, soc = simulate(nmc_profile, t, i, temp, 0.8, params=params)
    assert v.shape == soc.shape == (n, 3)
    v_ref, soc_ref = simulate(nmc_profile, t, i, temp, 0.8)
    np.testing.assert_allclose(v[:, 1], v_ref, atol=1e-12)
    np.testing.assert_allclose(soc[:, 0], soc_ref, atol=1e-14)
    # only R_ohm differs: the voltage difference is exactly ΔR·I
    np.testing.assert_allclose(v[:, 0] - v[:, 1], 0.5 * 0.02 * i, atol=1e-12)


# -- profile files ---------------------------------------------------------------------------
def _full_profile(nmc_profile_factory) -> CellProfile:
    return nmc_profile_factory(
        temps_c=(5.0, 25.0, 40.0),
        hysteresis=HysteresisSpec(u_h_max_v=0.012, rate=45.0),
        extensions=Extensions(
            current_bias_a=0.02,
            capacity_scale=0.97,
            arrhenius=ArrheniusSpec(ref_temp_c=25.0, ea_r_ohm_j_mol=2.0e4, entropic_v_per_k=1e-4),
            extra_branches=[BranchSpec(r=0.004, c=30000.0, alpha=0.95)],
            kinetics_i0_a=4.0,
            ocv_correction=OcvCorrectionSpec(soc=[0.0, 0.5, 1.0], delta_v=[0.0, 0.003, 0.0]),
        ),
    )


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_profile_save_load_round_trip(tmp_path: Path, nmc_profile_factory, suffix: str) -> None:
    prof = _full_profile(nmc_profile_factory)
    path = tmp_path / f"sub/cell{suffix}"
    save_profile(prof, path)
    assert not list(path.parent.glob("*.tmp"))
    loaded = load_profile(path)
    assert_same_profile(loaded, prof)
    a, b = prof.parameters_at(np.array([0.0, 17.0, 33.0])), loaded.parameters_at(np.array([0.0, 17.0, 33.0]))
    for k in a.__dict__:
        np.testing.assert_allclose(getattr(b, k), getattr(a, k), rtol=SAVED_REL_TOL, atol=0)
    np.testing.assert_allclose(loaded.ocv_table().ocv_v, prof.ocv_table().ocv_v, rtol=SAVED_REL_TOL, atol=0)
    if suffix == ".json":
        json.loads(path.read_text())  # a plain JSON document


def test_profile_without_optional_parts_round_trips(tmp_path: Path, nmc_profile: CellProfile) -> None:
    for name in ("p.toml", "p.json"):
        save_profile(nmc_profile, tmp_path / name)
        assert_same_profile(load_profile(tmp_path / name), nmc_profile)


#: a saved profile's floats keep 12 significant digits: read back, each is this close to the original
SAVED_REL_TOL = 1e-11
#: a float literal in a TOML or JSON text
FLOAT_LITERAL = re.compile(r"(?<![\w.])-?(\d+\.\d*(?:[eE][-+]?\d+)?|\d+[eE][-+]?\d+)")


def _significant_digits(literal: str) -> int:
    mantissa = re.split("[eE]", literal.lstrip("-"))[0].replace(".", "")
    return len(mantissa.lstrip("0").rstrip("0")) or 1


def _assert_close(got: object, want: object, where: str) -> None:
    if isinstance(want, dict):
        assert isinstance(got, dict) and got.keys() == want.keys(), where
        for k in want:
            _assert_close(got[k], want[k], f"{where}.{k}")
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for k, (g, w) in enumerate(zip(got, want, strict=True)):
            _assert_close(g, w, f"{where}[{k}]")
    elif isinstance(want, float):
        assert isinstance(got, float) and math.isclose(got, want, rel_tol=SAVED_REL_TOL, abs_tol=0.0), (where, got, want)
    else:
        assert got == want, where


def assert_same_profile(got: CellProfile, want: CellProfile) -> None:
    """Every field equal, floats within :data:`SAVED_REL_TOL` relative (what a save keeps)."""
    _assert_close(got.model_dump(mode="json"), want.model_dump(mode="json"), "profile")


@pytest.mark.parametrize("suffix", [".toml", ".json"])
@pytest.mark.parametrize("source", ["calce_a123", "noisy"])
def test_a_saved_profile_has_no_float_noise_and_reads_back_within_1e_11(tmp_path: Path, nmc_profile_factory,
                                                                         source: str, suffix: str) -> None:
    """`socd fit` wrote `0.17500000000000002` and `0.9999990000000001`: floats keep 12 significant digits
    on write, through lists of lists, and the profile in memory keeps all of its digits."""
    if source == "calce_a123":  # a bundled profile, its OCV table given the noise arithmetic leaves
        bundled = load_profile(profile_path("calce_a123.toml"))
        noisy_ocv = [[v + 3**0.5 * 1e-13 for v in row] for row in bundled.ocv.ocv_v]
        prof = bundled.model_copy(update={"ocv": bundled.ocv.model_copy(update={"ocv_v": noisy_ocv})})
    else:
        base = nmc_profile_factory(temps_c=(5.0, 25.0))
        prof = base.model_copy(update={
            "capacity_ah": 0.1 + 0.2,  # 0.30000000000000004
            "ocv": base.ocv.model_copy(update={"ocv_v": [[v + 0.1 * 3 for v in row] for row in base.ocv.ocv_v]}),
            "parameters": [pt.model_copy(update={"r_ohm": 0.1 * 1.75}) for pt in base.parameters],
        })
    before = prof.model_dump(mode="json")
    noisy = [x for x in FLOAT_LITERAL.findall(json.dumps(before)) if _significant_digits(x) >= 16]
    assert noisy, "the profile should carry float noise for this test to mean anything"
    path = tmp_path / f"cell{suffix}"
    save_profile(prof, path)
    text = path.read_text()
    assert max(_significant_digits(x) for x in FLOAT_LITERAL.findall(text)) <= 12
    assert_same_profile(load_profile(path), prof)
    assert prof.model_dump(mode="json") == before  # only the file is rounded


def _raw(prof: CellProfile) -> dict:
    return prof.model_dump(mode="json", exclude_none=True)


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d["parameters"][0].update(r_ohm=-0.01), "parameters.0.r_ohm"),
        (lambda d: d["parameters"][0].update(m=1.5), "parameters.0.m"),
        (lambda d: d.pop("capacity_ah"), "capacity_ah"),
        (lambda d: d.update(capacity_ah=0.0), "capacity_ah"),
        (lambda d: d.update(colour="blue"), "colour"),
        (lambda d: d["hysteresis"].update(u_h_max_v=-1.0), "hysteresis.u_h_max_v"),
        (lambda d: d["ocv"]["ocv_v"][0].pop(), "ocv"),
    ],
)
def test_load_profile_errors_name_file_and_field(tmp_path: Path, nmc_profile: CellProfile, mutate, field: str) -> None:
    raw = _raw(nmc_profile)
    mutate(raw)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(raw))
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    msg = str(exc.value)
    assert str(path) in msg
    assert field in msg


def test_load_profile_unreadable_and_invalid_syntax(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ProfileError, match="cannot read") as exc:
        load_profile(missing)
    assert str(missing) in str(exc.value)
    bad_toml = tmp_path / "bad.toml"
    bad_toml.write_text("capacity_ah = = 2\n")
    with pytest.raises(ProfileError, match="not valid TOML") as exc:
        load_profile(bad_toml)
    assert str(bad_toml) in str(exc.value)
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{capacity_ah: 2")
    with pytest.raises(ProfileError, match="not valid JSON") as exc:
        load_profile(bad_json)
    assert str(bad_json) in str(exc.value)
    a_dir = tmp_path / "dir.toml"
    a_dir.mkdir()
    with pytest.raises(ProfileError, match="cannot read"):
        load_profile(a_dir)
