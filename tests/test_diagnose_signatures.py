"""Signatures outside the voltage fit: the current-sensor offset measured in rests."""

from __future__ import annotations

import numpy as np
import pytest

from service.diagnosis.signatures import BIAS_MIN_Z, rest_current_offset, rest_runs, signatures

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
