"""Rests read on a noisy current sensor (:func:`service.characterisation.ocv_sources.resting`).

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

from service.characterisation.ocv_sources import (
    REST_CURRENT_C,
    REST_MAX_AVERAGE_S,
    REST_MIN_S,
    _runs,
    current_noise_a,
    load_level_a,
    rest_level_a,
    rest_points,
    rest_spans,
    resting,
)
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
