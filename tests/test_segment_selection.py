"""Which segments a fit keeps within its sample budget: every kind of a pulse test's segments, in
proportion to its share, spread over SOC, never more samples than the budget
(service.characterisation.segment_selection)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from service.cell.coulomb import coulomb_soc
from service.cell.fitting import FitSegment
from service.characterisation.characterise import MAX_FIT_SAMPLES, split_at_rests
from service.characterisation.fit_summary import TemperatureSummary
from service.characterisation.segment_selection import (
    segment_kind,
    select_segments,
    spread_order,
    van_der_corput,
)
from service.recording import load_recording

PAN = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "panasonic_18650pf"


def pulse_segment(amplitude_a: float, n: int, soc0: float) -> FitSegment:
    t = np.arange(n, dtype=float)
    i = np.where(t < 10, amplitude_a, 0.0)
    return FitSegment(t, i, 3.7 - 0.05 * i, np.full(n, 25.0), soc0)


def periodic_test(levels: int = 9) -> list[FitSegment]:
    """An HPPC-like list: at each SOC level pulses of 1.5, 2.9 and 5.8 A, then a short 11.6 A one."""
    segs = []
    for k in range(levels):
        soc = 1.0 - 0.1 * k
        segs += [pulse_segment(a, n, soc) for a, n in ((1.5, 1840), (2.9, 1840), (5.8, 1840), (11.6, 180))]
    return segs


def test_van_der_corput_and_spread_order_cover_the_range_evenly() -> None:
    assert [van_der_corput(k) for k in range(5)] == [0.0, 0.5, 0.25, 0.75, 0.125]
    for n in (1, 2, 7, 16, 33):
        for phase in (0.0, 0.618):
            assert sorted(spread_order(n, phase)) == list(range(n))
    assert sorted(spread_order(16)[:4]) == [0, 4, 8, 12]


def test_a_stride_that_matches_the_period_no_longer_drops_kinds() -> None:
    segs = periodic_test()
    budget = 16000
    kept = select_segments(segs, budget)
    assert sum(len(s) for s in kept) <= budget
    assert {segment_kind(s) for s in kept} == {segment_kind(s) for s in segs}
    # the rule it replaces (every k-th segment, k = ceil(total / budget) = 4 here) kept one kind
    stride = int(np.ceil(sum(len(s) for s in segs) / budget))
    assert len({segment_kind(s) for s in segs[::stride]}) == 1
    # the three long kinds share the budget about equally, as they share the recording
    long_counts = [n for kind, n in Counter(segment_kind(s) for s in kept).items() if kind[1] > 8]
    assert max(long_counts) - min(long_counts) <= 1
    # spread over SOC, in recording order
    socs = [s.soc0 for s in kept]
    assert socs == sorted(socs, reverse=True)
    assert max(socs) - min(socs) >= 0.6


def test_everything_is_kept_within_budget_and_one_segment_at_least() -> None:
    segs = periodic_test(2)
    assert select_segments(segs, 10**6) == segs
    tiny = select_segments(segs, 10)
    assert len(tiny) == 1 and len(tiny[0]) == min(len(s) for s in segs)


@pytest.mark.skipif(not (PAN / "pan18650pf_m20C_HPPC.csv").exists(), reason="shared Panasonic data not present")
def test_the_cold_hppc_test_keeps_every_kind_of_its_segments() -> None:
    rec = load_recording(PAN / "pan18650pf_m20C_HPPC.csv")
    soc = coulomb_soc(rec.time_s, rec.current_a, 2.77, 1.0)
    segs = [s for s in split_at_rests(rec, soc, 2.77) if s.soc0 >= 0.1]
    kept = select_segments(segs, MAX_FIT_SAMPLES)
    assert sum(len(s) for s in kept) <= MAX_FIT_SAMPLES
    assert {segment_kind(s) for s in kept} == {segment_kind(s) for s in segs}
    peaks = [float(np.abs(s.current_a).max()) for s in kept]
    assert min(peaks) < 2.0 and max(peaks) > 11.0  # the 1.5 A pulses and the 11.6 A ones


def test_a_fit_on_a_subsample_reads_its_point_on_every_segment_too(nmc_recording, monkeypatch) -> None:
    """Where the search sees a subsample, the fit log and report give the point's RMSE over every
    segment as well, so a subsample that does not stand for the recording shows; a fit that saw
    everything gives no second figure. The real fit runs on a simulated cell with three segments, the
    budget cut to hold two of them."""
    import service.characterisation.characterise as ch

    rec = load_recording(nmc_recording(name="subsample", duration_s=7200, seed=4, soc0=0.95).path)
    _, whole_fit = ch.characterise([rec], 2.0, [None], fit_kinetics=False, max_seconds=2)
    assert whole_fit.temperatures[0].whole_rmse_mv is None
    monkeypatch.setattr(ch, "MAX_FIT_SAMPLES", 3000)
    _, report = ch.characterise([rec], 2.0, [None], fit_kinetics=False, max_seconds=2)
    (t,) = report.temperatures
    # the budget holds the two short segments (SOC above 0.95) but not the long discharge to 0.43:
    # the OCV fitted jointly on the subsample does not know that range, and the second figure shows it
    assert t.whole_rmse_mv is not None and t.whole_rmse_mv > 3.0 * t.rmse_mv
    assert TemperatureSummary.of(t).whole_rmse_mv == pytest.approx(t.whole_rmse_mv)
    line = next(x for x in report.lines if "the search saw" in x)
    assert "2 of 3 segments" in line and f"{t.whole_rmse_mv:.1f} mV" in line
