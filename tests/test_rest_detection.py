"""Rests read on a noisy current sensor (:func:`service.cell.rests.resting`).

A rest is ``|I| < 1 % of 1C``.  On a small cell a current sensor's noise alone exceeds that (5 mA on a
0.17 Ah cell's 1.7 mA, PyBaMM's ``Ecker2015`` as ``research.unseen_cell`` builds it), so read sample by
sample no rest lasts the ten minutes ``socd fit`` anchors its OCV table on, and a fit from a pulse test
alone has no rest to anchor at.  The recordings here are HPPC-like: rests of 20 minutes between 1C
steps and pulses, sampled at 1 Hz.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.cell.rests import (
    REST_CURRENT_C,
    REST_MAX_AVERAGE_S,
    current_noise_a,
    load_level_a,
    rest_level_a,
    resting,
)
from service.characterisation.ocv_sources import REST_MIN_S, _runs, rest_points, rest_spans
from service.diagnosis.pipeline import opening_rest_end
from service.diagnosis.signatures import REST_MAX_C, rest_current_offset, rest_runs
from service.recording import Recording

SMALL_AH = 0.17
NOISE_A = 0.005
REST_S = 1200


def hppc_like(capacity_ah: float, noise_a: float, seed: int = 0) -> tuple[Recording, list[tuple[int, int]]]:
    """Eight rounds of: rest, 10 s pulse at 1C, 40 s rest, 10 s charge pulse, rest, 6 min at 1C;
    then a closing rest.  Returns the recording and the ``[first, last]`` samples of each long rest."""
    steps: list[tuple[int, float]] = []
    for _ in range(8):
        steps += [(REST_S, 0.0), (10, 1.0), (40, 0.0), (10, -0.75), (REST_S, 0.0), (360, 1.0)]
    steps.append((REST_S, 0.0))
    current, rests, k = [], [], 0
    for dur, c_rate in steps:
        current += [c_rate * capacity_ah] * dur
        if c_rate == 0.0 and dur == REST_S:
            rests.append((k, k + dur - 1))
        k += dur
    i_true = np.array(current)
    rng = np.random.default_rng(seed)
    i = i_true + rng.normal(0.0, noise_a, i_true.size)
    t = np.arange(i.size, dtype=float)
    v = 3.7 - 0.05 * i_true  # the voltage plays no part in finding rests
    return Recording(Path(f"hppc_{capacity_ah:g}Ah.csv"), t, i, v, np.full(t.size, 25.0)), rests


def test_the_sensor_noise_is_read_from_the_rests():
    rec, _ = hppc_like(SMALL_AH, NOISE_A)
    assert current_noise_a(rec.current_a, SMALL_AH) == pytest.approx(NOISE_A, rel=0.15)
    clean, _ = hppc_like(SMALL_AH, 0.0)
    assert current_noise_a(clean.current_a, SMALL_AH) == 0.0


def test_an_offset_and_a_drives_light_loads_are_not_read_as_noise():
    """The noise is what the current changes by from sample to sample near zero: a sensor offset
    (0.8 % of 1C on a 1 Ah cell) and a drive's light loads (coasting at 1-4 % of 1C, changing every 10 s) move
    the level, not that spread.  Read as the spread about zero they made the noise several times
    the sensor's (a recorded drive cycle's rests then took in loads of 20 % of 1C)."""
    rec, _ = hppc_like(1.0, NOISE_A, seed=5)
    offset = rec.current_a + 0.008
    assert current_noise_a(offset, 1.0) == pytest.approx(NOISE_A, rel=0.15)
    rng = np.random.default_rng(6)
    coasting = np.repeat(rng.uniform(0.01, 0.04, 300), 10) * 5.0
    drive = np.concatenate([rng.normal(0.0, 1e-3, 600), coasting + rng.normal(0.0, 1e-3, coasting.size)])
    assert current_noise_a(drive, 5.0) == pytest.approx(1e-3, rel=0.2)
    assert rest_level_a(drive, 5.0) == REST_CURRENT_C * 5.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_rest_of_a_small_cell_is_found_through_the_noise(seed):
    """Each 20-minute rest is one span, inside the true rest and covering most of it; the same
    recording tested sample by sample against 1 % of 1C has no rest of ten minutes at all."""
    rec, rests = hppc_like(SMALL_AH, NOISE_A, seed)
    per_sample = np.abs(rec.current_a) < REST_CURRENT_C * SMALL_AH
    longest = max(b - a for a, b in _runs(per_sample))
    assert longest < REST_MIN_S, longest
    spans = rest_spans(rec, SMALL_AH, REST_MIN_S)
    assert len(spans) == len(rests), spans
    for (a, b), (ta, tb) in zip(spans, rests):
        assert ta <= a and b <= tb, ((a, b), (ta, tb))
        assert b - a + 1 >= 0.95 * REST_S
    assert len(rest_points(rec, SMALL_AH, 1.0)) == len(rests)


def test_a_clean_logger_keeps_the_sample_by_sample_rule():
    """A logger that writes rests as zeros, and a large cell whose noise is well under 1 % of 1C,
    read rests exactly as the plain threshold does (no averaging, no trimmed edges)."""
    for capacity_ah, noise_a in ((SMALL_AH, 0.0), (5.0, NOISE_A)):
        rec, rests = hppc_like(capacity_ah, noise_a)
        plain = np.abs(rec.current_a) < REST_CURRENT_C * capacity_ah
        np.testing.assert_array_equal(resting(rec.time_s, rec.current_a, capacity_ah), plain)
        assert rest_level_a(rec.current_a, capacity_ah) == REST_CURRENT_C * capacity_ah
        assert load_level_a(rec.current_a, capacity_ah) == 5 * REST_CURRENT_C * capacity_ah
    rec, rests = hppc_like(SMALL_AH, 0.0)
    assert rest_spans(rec, SMALL_AH, REST_MIN_S) == rests


def test_a_slow_test_current_under_the_noise_is_not_a_rest():
    """C/20 on the small cell (8.5 mA) is below the noise's 5σ but far above its mean over a rest:
    an OCV test's branch is not read as a rest beyond the half window a rest may reach into it, and
    the rests on either side are read up to their edges."""
    n = 4000
    rng = np.random.default_rng(3)
    slow = SMALL_AH / 20 + rng.normal(0.0, NOISE_A, n)
    quiet = rng.normal(0.0, NOISE_A, n)
    current = np.concatenate([quiet, slow, quiet])
    rest = resting(np.arange(current.size, dtype=float), current, SMALL_AH)
    half = int(REST_MAX_AVERAGE_S) // 2
    assert not rest[n + half:2 * n - half].any()
    assert rest[n - 1] and rest[2 * n]
    assert rest[:n].mean() > 0.99 and rest[2 * n:].mean() > 0.99
    assert load_level_a(current, SMALL_AH) >= rest_level_a(current, SMALL_AH) > REST_CURRENT_C * SMALL_AH


@pytest.mark.parametrize("bias_c", [0.0, 0.002, -0.004, 0.008])
def test_the_diagnosis_reads_a_small_cells_rests_and_sensor_offset_through_the_noise(bias_c):
    """``socd diagnose``'s rest test (3 % of 1C, :data:`REST_MAX_C`) on the small cell: its noise
    crosses that level too (5 mA over 5.1 mA), and read sample by sample the current-offset
    signature found no rest on such a cell and measured nothing.  Read through the noise it finds
    every long rest and the sensor's offset within its standard error (nominating it from 0.2 % of
    1C, not at 0), and the opening rest ends where the first pulse begins."""
    rec, rests = hppc_like(SMALL_AH, NOISE_A, seed=4)
    bias_a = bias_c * SMALL_AH
    current = rec.current_a + bias_a
    per_sample = np.abs(current) < REST_MAX_C * SMALL_AH
    assert max(b - a for a, b in _runs(per_sample)) < 200
    runs = [r for r in rest_runs(rec.time_s, current, SMALL_AH) if r[1] - r[0] >= 0.9 * REST_S]
    assert len(runs) == len(rests)
    sig = rest_current_offset(rec.time_s, current, SMALL_AH)
    assert abs(sig["offset_a"] - bias_a) <= 3 * sig["se_a"] + 1e-5
    assert sig["nominated"] == (bias_c != 0.0)  # 0.2 % of 1C is the development set's subtle offset
    shifted = Recording(rec.path, rec.time_s, current, rec.voltage_v, rec.temperature_c)
    assert REST_S - REST_MAX_AVERAGE_S / 2 <= opening_rest_end(shifted, SMALL_AH) + 1 <= REST_S
