"""Signatures outside the voltage fit: the current-sensor offset measured in rests, the two-point capacity."""

from __future__ import annotations

import numpy as np
import pytest

from service.cell.profile import OcvSpec
from service.diagnosis.signatures import (
    BIAS_MIN_Z,
    capacity_end_point,
    rest_current_offset,
    rest_runs,
    signatures,
    two_point_capacity,
)

CAP = 5.0


def drive(seed: int = 1, hours: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """1 Hz true current: load steps (some small, below 3 % of 1C) and rests of 20 s to 5 min."""
    rng = np.random.default_rng(seed)
    out: list[float] = [0.0] * 60
    while len(out) < hours * 3600:
        out += [float(rng.choice([2.0, 1.0, 0.5, 0.3, -0.5]) * CAP)] * int(rng.integers(5, 120))
        if rng.random() < 0.3:
            out += [0.0] * int(rng.integers(20, 300))
    i = np.array(out[: int(hours * 3600)])
    return np.arange(i.size, dtype=float), i


def measured(i_true: np.ndarray, bias_a: float, seed: int = 2) -> np.ndarray:
    """The synthetic data's sensor: true + offset + N(0, 0.5 % |I| + 5 mA), written at 0.1 mA."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, 1.0, i_true.size) * (0.005 * np.abs(i_true) + 0.005)
    return np.round(i_true + bias_a + noise, 4)


@pytest.mark.parametrize("bias_a", [-0.02, 0.006, 0.04])
def test_rest_current_finds_a_known_offset_within_its_standard_error(bias_a):
    t, i = drive()
    sig = rest_current_offset(t, measured(i, bias_a), CAP)
    assert sig["nominated"], sig
    assert abs(sig["offset_a"] - bias_a) < 4 * sig["se_a"], sig
    assert sig["se_a"] < 5e-4  # hundreds of rest samples: a fraction of a mA
    assert sig["statistic"] >= BIAS_MIN_Z


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_rest_current_does_not_nominate_a_calibrated_sensor(seed):
    t, i = drive(seed)
    sig = signatures(t, measured(i, 0.0, seed), np.full(t.size, 25.0), CAP)["current_bias"]
    assert not sig["nominated"], sig
    assert abs(sig["offset_a"]) < 4 * sig["se_a"]


def test_small_load_steps_and_spikes_are_not_rests():
    """A long 0.02C trickle is constant and below 3 % of 1C, but its level disagrees with the rests."""
    t, i = drive(6)
    i[2000:2600] = 0.02 * CAP  # a trickle load, not a rest
    i_meas = measured(i, 0.0, 6)
    runs = rest_runs(t, i_meas, CAP)
    assert all(not (a < 2600 and b > 2000) for a, b in runs)
    spiky = i_meas.copy()
    a, b = runs[0]
    spiky[(a + b) // 2] = 0.1  # one spike inside a rest
    sig = rest_current_offset(t, spiky, CAP)
    assert not sig["nominated"] and abs(sig["offset_a"]) < 4 * sig["se_a"]


def test_no_rests_no_measurement():
    t = np.arange(3000.0)
    i = 1.0 + 0.5 * np.sin(t / 50.0)
    sig = rest_current_offset(t, i, CAP)
    assert not sig["nominated"] and sig["n_rest_samples"] == 0 and sig["se_a"] is None


# -- two-point capacity ---------------------------------------------------------------------------
def _two_point(scale: float, tail: str = "rest", sign: float = 1.0, polarisation_error: float = 0.0,
               ocv: OcvSpec | None = None, seed: int = 4) -> dict:
    """A cell with ``scale`` x the stated capacity, discharged (``sign`` -1: charged) from a
    relaxed opening rest; the recording ends in a 10-min rest after 70 % of the true capacity,
    or under 2C load after 88 % (a cut-off near empty, where the OCV is steep) (``tail``).
    The model the check is given is the true one at the *stated* capacity, with its
    polarisation off by ``polarisation_error`` (a fraction)."""
    from research.validate import TRUE, base_profile
    from service.cell.profile import Extensions
    from service.cell.trajectory import simulate

    stated = base_profile() if ocv is None else base_profile().model_copy(update={"ocv": ocv})
    cap = stated.capacity_ah
    rng = np.random.default_rng(seed)
    soc0 = 0.95 if sign > 0 else 0.10
    i = [0.0] * 60
    drawn = 0.0
    while drawn < (0.70 if tail == "rest" else 0.86) * scale * cap * 3600:
        level = sign * float(rng.choice([2.0, 1.0, 0.5])) * cap
        n = int(rng.integers(20, 200))
        i += [level] * n
        drawn += abs(level) * n
    if tail == "rest":
        i += [0.0] * 600
    elif tail == "load":
        i += [sign * 2.0 * cap] * 30
    elif tail == "pause":  # a minute's pause, then a last 2C burst into the cut-off
        i += [0.0] * 60 + [sign * 2.0 * cap] * 30
    else:  # "long pause": ten minutes' rest, then a last 2C burst into the cut-off
        i += [0.0] * 600 + [sign * 2.0 * cap] * 30
    i_true = np.array(i)
    t = np.arange(i_true.size, dtype=float)
    temp = np.full(t.size, 25.0)
    cell = stated.model_copy(update={"extensions": Extensions(capacity_scale=scale)})
    v, _ = simulate(cell, t, i_true, temp, soc0)
    v = v + rng.normal(0.0, 0.001, t.size)
    model = stated.model_copy(update={"parameters": [TRUE.model_copy(update={
        "r_ct": TRUE.r_ct * (1 + polarisation_error), "r_df": TRUE.r_df * (1 + polarisation_error)})]})
    v_model, soc_model = simulate(model, t, i_true, temp, soc0)
    return two_point_capacity(t, i_true, v, temp, v_model, soc_model, model.ocv_table(), cap, 59,
                              capacity_end_point(t, i_true, cap), TRUE.r_ohm)


@pytest.mark.parametrize("tail", ["rest", "load"])
def test_two_point_capacity_measures_a_faded_cell(tail):
    sig = _two_point(0.85, tail)
    assert sig["nominated"], sig
    assert sig["capacity_scale"] == pytest.approx(0.85, abs=0.015), sig
    lo, hi = sig["capacity_scale_range"]
    assert lo <= 0.85 <= hi


def test_two_point_capacity_range_covers_the_truth_with_a_wrong_model():
    """Polarisation 60 % too high in the model: the point moves, the range still holds the truth."""
    sig = _two_point(0.85, "load", polarisation_error=0.6)
    lo, hi = sig["capacity_scale_range"]
    assert lo <= 0.85 <= hi, sig


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_two_point_capacity_does_not_nominate_a_healthy_cell(seed):
    for tail in ("rest", "load"):
        sig = _two_point(1.0, tail, seed=seed)
        assert not sig["nominated"], sig
        lo, hi = sig["capacity_scale_range"]
        assert lo <= 1.0 <= hi, sig


def test_two_point_capacity_on_a_charge():
    sig = _two_point(0.85, "rest", sign=-1.0)
    assert sig["drawn_soc"] < 0 and sig["nominated"], sig
    assert sig["capacity_scale"] == pytest.approx(0.85, abs=0.015), sig


def test_two_point_capacity_flat_ocv_widens_the_range():
    """An LFP-like plateau: the rest SOCs are poorly pinned, so a 5 % fade is not claimed."""
    soc = np.linspace(0, 1, 41)
    flat = 3.2 + 0.1 * soc + 0.25 * np.tanh((soc - 0.04) / 0.03) + 0.1 * np.tanh((soc - 0.985) / 0.01)
    sig = _two_point(0.95, "rest", ocv=OcvSpec(soc=soc.tolist(), ocv_v=[flat.tolist()]))
    assert not sig["nominated"], sig
    lo, hi = sig["capacity_scale_range"]
    assert hi - lo > 0.1 and lo <= 0.95 <= hi, sig


def test_two_point_capacity_needs_an_opening_rest():
    """A recording that opens under load has no OCV-anchored start: nothing is measured."""
    t = np.arange(2000, dtype=float)
    i = np.full(t.size, 5.0)
    v = np.linspace(4.1, 3.4, t.size)
    from research.validate import base_profile

    table = base_profile().ocv_table()
    sig = two_point_capacity(t, i, v, np.full(t.size, 25.0), v, np.linspace(0.9, 0.3, t.size), table, 2.0, 0,
                             t.size - 1, 0.03)
    assert not sig["nominated"] and "opening rest" in sig["skipped"]


def test_two_point_capacity_end_is_the_lightest_load_before_a_cut_off():
    """A burst into the cut-off after a pause: the check reads the pause, not the burst, so a
    model that badly underrates the polarisation under load does not fake a fade."""
    t = np.arange(400, dtype=float)
    i = np.r_[np.full(250, 4.0), np.zeros(60), np.full(90, 8.0)]
    assert capacity_end_point(t, i, 2.0) == 309  # the pause's last sample
    assert capacity_end_point(t, np.r_[np.full(300, 4.0), np.full(100, 2.0)], 2.0) == 300  # lightest load
    sig = _two_point(1.0, "pause", polarisation_error=-0.9)
    assert not sig["nominated"] and sig["capacity_scale_range"][0] <= 1.0 <= sig["capacity_scale_range"][1], sig


@pytest.mark.parametrize("scale", [0.85, 1.0])
def test_two_point_capacity_reads_a_long_rest_by_its_relaxation_not_the_model(scale):
    """Ten minutes' rest before a last burst into the cut-off: the check closes at that rest's end
    and bounds its OCV by the rest's own relaxation, so a model whose polarisation is four times
    the cell's (the fit part's extrapolation to empty) neither hides a 15 % fade nor fakes one."""
    sig = _two_point(scale, "long pause", polarisation_error=3.0)
    assert sig["end_bound"] == "relaxation", sig
    lo, hi = sig["capacity_scale_range"]
    assert lo <= scale <= hi and sig["nominated"] == (scale < 1.0), sig
    assert sig["capacity_scale"] == pytest.approx(scale, abs=0.02), sig
    assert _two_point(scale, "pause", polarisation_error=3.0)["end_bound"] == "model"  # a minute's pause


def _thermal(t: np.ndarray, i: np.ndarray, t_start: float, t_amb: np.ndarray, tau_s: float = 900.0,
             heat_k: float = 2.0) -> np.ndarray:
    """A lumped cell temperature: ``τ dT/dt = T_amb(t) + heat·(I/C)² − T`` from ``t_start``, 0.1 °C noise."""
    temp = np.empty(t.size)
    temp[0] = t_start
    for k in range(1, t.size):
        target = t_amb[k] + heat_k * (i[k] / CAP) ** 2
        temp[k] = target + (temp[k - 1] - target) * np.exp(-(t[k] - t[k - 1]) / tau_s)
    return temp + np.random.default_rng(5).normal(0.0, 0.1, t.size)


def test_a_cold_start_that_warms_smoothly_is_nominated_by_its_opening_temperature():
    """An ambient moving smoothly from 10 °C to 25 °C is one first-order lag, which the
    constant-ambient model fits (misfit below its 0.5 K bar); the opening 15 K from the nominal
    ambient, with the temperature then moving, nominates it."""
    t, i = drive(3, hours=2.0)
    t_amb = 25.0 - 15.0 * np.exp(-t / 2500.0)
    temp = _thermal(t, i, 10.0, t_amb)
    sig = signatures(t, i, temp, CAP)["temperature"]
    assert sig["rms_k"] < 0.5
    assert sig["nominated"]
    assert sig["opening_temp_c"] == pytest.approx(10.0, abs=0.3)
    assert "opens" in sig["why"]
    assert sig["direct"], "an ambient measured away from the nominal one is the departure itself"
    # without a nominal ambient only the misfit counts
    assert not signatures(t, i, temp, CAP, nominal_ambient_c=None)["temperature"]["nominated"]


def test_a_warm_start_that_cools_smoothly_is_nominated_by_its_coldest_temperature():
    """A cell opening at the nominal 25 °C in a 10 °C ambient cools along one first-order lag
    (misfit below its bar, opening nominal); the cell falling 15 K below the nominal
    ambient, which self-heating cannot do, nominates it."""
    t, i = drive(3, hours=2.0)
    temp = _thermal(t, i, 25.0, np.full(t.size, 10.0), tau_s=2500.0)
    sig = signatures(t, i, temp, CAP)["temperature"]
    assert sig["rms_k"] < 0.5 and sig["opening_temp_c"] == pytest.approx(25.0, abs=0.5)
    assert sig["nominated"] and "cools" in sig["why"], sig
    assert sig["direct"]
    assert sig["coldest_temp_c"] < 20.0
    assert not signatures(t, i, temp, CAP, nominal_ambient_c=None)["temperature"]["nominated"]


def test_a_warm_spell_from_the_nominal_ambient_nominates_but_does_not_measure():
    """The ambient steps from the nominal 25 °C to 35 °C and back: the constant-ambient model
    misfits it (nominated), but the recording neither opens away from the nominal ambient nor
    cools below it, so nothing measured says the cell ran at another temperature than the base
    model's (a cell that heats differently, e.g. slow kinetics, reads the same): not direct."""
    t, i = drive(3, hours=2.0)
    t_amb = np.where((t > 2000) & (t < 5000), 35.0, 25.0)
    sig = signatures(t, i, _thermal(t, i, 25.0, t_amb), CAP)["temperature"]
    assert sig["nominated"] and "constant ambient" in sig["why"], sig
    assert not sig["direct"]


@pytest.mark.parametrize(("t_start", "t_amb_c", "heat_k"), [(25.0, 25.0, 2.0), (0.0, 0.0, 0.2), (27.0, 25.0, 2.0)])
def test_a_nominal_or_constant_temperature_recording_is_not_nominated(t_start, t_amb_c, heat_k):
    """Self-heating at the nominal ambient, a cold chamber that holds its temperature (a cold
    recording is modelled by the base fit, not by a temperature law), and a cell that opens 2 K
    warm after its charge: none is nominated."""
    t, i = drive(4, hours=2.0)
    temp = _thermal(t, i, t_start, np.full(t.size, t_amb_c), heat_k=heat_k)
    sig = signatures(t, i, temp, CAP)["temperature"]
    assert not sig["nominated"], sig


# -- kinetics: the curvature of the voltage across current steps ---------------------------------
@pytest.mark.parametrize(("level", "i0_c"), [("clear", 0.03), ("moderate", 0.06)])
def test_current_steps_measure_a_slow_exchange_current(level, i0_c):
    """The estimator's own model with a Butler-Volmer term (research.validate's grid,
    i0 0.03 / 0.06 C): the step statistic finds i0 within 10 % and nominates kinetics."""
    from research.validate import CAP as GRID_CAP
    from research.validate import simulate_case
    from service.diagnosis.signatures import step_kinetics

    for seed in (0, 1):
        c = simulate_case("kinetics", level, seed)
        k = step_kinetics(c[:, 0], c[:, 1], c[:, 2], c[:, 3], GRID_CAP)
        assert k["nominated"], k
        assert k["i0_c"] == pytest.approx(i0_c, rel=0.10)
        assert k["i0_upper_c"] < 0.1 and k["n_steps"] >= 20


@pytest.mark.parametrize("effect", ["none", "diffusion", "hysteresis", "temperature"])
def test_current_steps_of_a_linear_cell_do_not_nominate_kinetics(effect):
    """Without a Butler-Volmer term the steps are linear in the current (every other effect of
    the grid is linear or slow), whatever else the cell does."""
    from research.validate import CAP as GRID_CAP
    from research.validate import simulate_case
    from service.diagnosis.signatures import step_kinetics

    for seed in (0, 1):
        c = simulate_case(effect, "clear", seed)
        k = step_kinetics(c[:, 0], c[:, 1], c[:, 2], c[:, 3], GRID_CAP)
        assert not k["nominated"], k
        assert k["i0_upper_c"] > 0.1


def test_current_steps_outside_the_usable_part_or_too_few_are_not_read():
    from research.validate import CAP as GRID_CAP
    from research.validate import simulate_case
    from service.diagnosis.signatures import STEP_MIN_STEPS, step_kinetics

    c = simulate_case("kinetics", "clear", 0)
    t, i, v, temp = c.T
    none_usable = step_kinetics(t, i, v, temp, GRID_CAP, usable=np.zeros(t.size, bool))
    assert none_usable["n_steps"] == 0 and not none_usable["nominated"] and "needs" in none_usable["skipped"]
    half = step_kinetics(t, i, v, temp, GRID_CAP, usable=t < t[t.size // 2])
    whole = step_kinetics(t, i, v, temp, GRID_CAP)
    assert 0 < half["n_steps"] < whole["n_steps"]
    # a smooth current (a ramp) has no steps between two samples
    ramp = np.linspace(0.0, 2.0 * GRID_CAP, t.size)
    smooth = step_kinetics(t, ramp, 4.0 - 0.02 * ramp, temp, GRID_CAP)
    assert smooth["n_steps"] < STEP_MIN_STEPS and not smooth["nominated"]


# -- hysteresis on a drive cycle: the direction state in the base residual -------------------------
def _lowpassed(x: np.ndarray, t: np.ndarray, tau: float) -> np.ndarray:
    from service.diagnosis.features import lowpass

    return lowpass(x, t, tau)


def test_direction_state_in_the_residual_nominates_hysteresis_beyond_any_linear_polarisation():
    """A residual that holds a 12 mV branch voltage (Eq. 1, rate 100) on top of polarisation the base
    model got wrong (two low-passed currents) and noise: the half-gap is found and nominated; the
    same residual without the branch voltage is not, however large the polarisation error."""
    from service.diagnosis.features import direction_state
    from service.diagnosis.signatures import DIRECTION_MIN_Z, direction_offset

    t, i = drive(seed=3, hours=3.0)
    rng = np.random.default_rng(3)
    crate = i / CAP
    polarisation = 0.015 * _lowpassed(crate, t, 40.0) - 0.008 * _lowpassed(crate, t, 400.0)
    noise = rng.normal(0.0, 0.0015, t.size)
    usable = t < 0.6 * t[-1]
    branch = 0.012 * direction_state(t, i, CAP, 100.0)
    with_branch = direction_offset(t, i, branch - polarisation + noise, CAP, usable)
    assert with_branch["nominated"] and with_branch["statistic"] >= DIRECTION_MIN_Z, with_branch
    assert with_branch["half_gap_v"] == pytest.approx(0.012, rel=0.15)
    without = direction_offset(t, i, -polarisation + noise, CAP, usable)
    assert not without["nominated"] and abs(without["statistic"]) < DIRECTION_MIN_Z, without
    # the wrong sign (the discharge branch above the table) is not hysteresis
    assert not direction_offset(t, i, -branch - polarisation + noise, CAP, usable)["nominated"]
    # too short a usable part: skipped, not nominated
    short = direction_offset(t, i, branch + noise, CAP, t < 900.0)
    assert not short["nominated"] and "needs" in short["skipped"]
