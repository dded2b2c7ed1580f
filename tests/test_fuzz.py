"""Property-based fuzzing (hypothesis) of the two doors hostile input comes through: CAN
frames with arbitrary timestamps and payloads into the real decoder, and arbitrary files
into the recording and CAN-log validation.  Examples are few and small so each test runs
in seconds; hypothesis' shrinking names the smallest failing input if one turns up.
"""

from __future__ import annotations

import math
from pathlib import Path

import can
import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from replay.pack import FrameBuilder
from service.bus.decoder import FRAME_ACCEPTS, REJECT_REASONS, FrameDecoder
from service.cli import UserError
from service.config import build_config
from service.validation import DEFAULT_BOUNDS, InputFileError, check_can_log

N = 8
CONFIG = build_config({"pack": {"n_cells": N}})
DT = 0.1
T0 = 1000.0
N_SAMPLES = 40


def _good_frames() -> list[can.Message]:
    b = FrameBuilder(CONFIG)
    out: list[can.Message] = []
    for k in range(N_SAMPLES):
        out += b.frames_for_sample(T0 + k * DT, 5.0 + 0.1 * k, 3.6 + 0.01 * np.arange(N), np.array([25.0, 26.0]))
    return out


GOOD = _good_frames()
PER_SAMPLE = len(GOOD) // N_SAMPLES
KNOWN_IDS = sorted({f.arbitration_id for f in GOOD})

timestamps = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=T0 - 50, max_value=T0 + 50),  # near the timeline: the hard cases
    st.sampled_from([0.0, -1.0, 1e6, T0 + 1e6, -T0, 1e308, -1e308]),
)


@st.composite
def hostile_frames(draw) -> can.Message:
    kind = draw(st.sampled_from(["data", "data", "data", "remote", "error"]))
    arb = draw(st.one_of(st.sampled_from(KNOWN_IDS), st.integers(0, 0x1FFFFFFF)))
    ext = arb > 0x7FF or draw(st.booleans())
    ts = draw(timestamps)
    if kind == "remote":
        return can.Message(timestamp=ts, arbitration_id=arb, is_extended_id=ext, is_remote_frame=True, dlc=8)
    if kind == "error":
        return can.Message(timestamp=ts, arbitration_id=arb & 0x1FFFFFFF, is_error_frame=True, dlc=8)
    data = draw(st.one_of(st.binary(min_size=8, max_size=8), st.binary(max_size=8),
                          st.binary(min_size=9, max_size=64)))
    return can.Message(timestamp=ts, arbitration_id=arb, is_extended_id=ext, data=data, is_fd=len(data) > 8)


def _counted_once(c) -> bool:
    return c["frames_in"] == sum(c[k] for k in FRAME_ACCEPTS) + sum(c[r] for r in REJECT_REASONS)


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(bad=hostile_frames(), where=st.integers(PER_SAMPLE, len(GOOD) - 1))
def test_one_hostile_frame_in_a_good_stream(bad: can.Message, where: int) -> None:
    """Any single frame (any timestamp, any payload) costs at most one good sample and is
    counted exactly once."""
    dec = FrameDecoder(CONFIG)
    samples = []
    for f in GOOD[:where] + [bad] + GOOD[where:]:
        samples += dec.feed(f)
    c = dec.counters
    assert c["frames_in"] == len(GOOD) + 1 and _counted_once(c)
    # good samples lost: at most the one the bad frame may have spoiled (a bad current
    # value, a voltage frame that invalidated its cells for one sample, a timestamp a
    # little ahead that its ID's next good frame rolls back from)
    good_times = {round(f.timestamp, 6) for f in GOOD}
    emitted = [s for s in samples if round(s.t_s, 6) in good_times]
    lost = N_SAMPLES - len({round(s.t_s, 6) for s in emitted})
    assert lost <= 1, (lost, bad)
    for s in samples:  # nothing implausible ever reaches the estimator as fresh
        v = s.voltage_v[s.fresh]
        assert np.all((v >= CONFIG.mapping.voltage_range_v[0]) & (v <= CONFIG.mapping.voltage_range_v[1]))
        assert math.isfinite(s.t_s) and math.isfinite(s.current_a)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(frames=st.lists(hostile_frames(), max_size=60))
def test_any_frame_sequence_is_counted_exactly_once(frames: list[can.Message]) -> None:
    dec = FrameDecoder(CONFIG)
    for f in frames:
        for s in dec.feed(f):
            assert math.isfinite(s.t_s)
    assert dec.counters["frames_in"] == len(frames) and _counted_once(dec.counters)


# -- files ----------------------------------------------------------------------------------
numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**6, 10**6).map(str),
    st.sampled_from(["", " ", "nan", "-inf", "1e308", "-1e308", "3.7", "abc", "1,5", "0x10", "\u00a0"]),
)
headers = st.one_of(
    st.just("time_s,current_a,voltage_v,temperature_c"),
    st.just("time_s,current_a,voltage_v,temperature_c,soc_true"),
    st.just("\ufefftime_s,current_a,voltage_v,temperature_c"),
    st.just("time_s;current_a;voltage_v;temperature_c"),
    st.text(max_size=40),
)


@st.composite
def recording_texts(draw) -> bytes:
    if draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=400))
    header = draw(headers)
    n_cols = draw(st.integers(1, 6))
    rows = draw(st.lists(st.lists(numbers, min_size=n_cols, max_size=n_cols), max_size=12))
    if draw(st.booleans()):  # mostly plausible rows, one value hostile: the common real case
        rows = [[str(k), "1.0", "3.7", "25"] + ([] if "soc_true" not in header else ["0.5"]) for k in range(8)]
        r, c = draw(st.integers(0, 7)), draw(st.integers(0, 3))
        rows[r][c] = draw(numbers)
    sep = draw(st.sampled_from([",", ",", ";", "\t"]))
    text = header + "\n" + "\n".join(sep.join(r) for r in rows) + draw(st.sampled_from(["", "\n", "\r\n"]))
    return text.encode(draw(st.sampled_from(["utf-8", "utf-8", "utf-16", "latin-1"])), errors="replace")


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(content=recording_texts())
# a quoted header field holding a line break: the error once showed the header with it
@example(content=b'"0\n0.0')
def test_any_recording_file_loads_valid_or_fails_in_one_line(tmp_path: Path, content: bytes) -> None:
    from service.recording import load_recording

    path = tmp_path / "rec.csv"
    path.write_bytes(content)
    try:
        rec = load_recording(path)
    except UserError as exc:
        msg = str(exc)
        assert msg.startswith(str(path)) and "\n" not in msg, msg
        return
    # accepted: then it is what every tool may rely on
    assert len(rec) >= 2 and np.all(np.diff(rec.time_s) > 0)
    for name in ("time_s", "current_a", "voltage_v", "temperature_c"):
        v = getattr(rec, name)
        lo, hi = DEFAULT_BOUNDS.of(name)
        assert np.all(np.isfinite(v)) and np.all((v >= lo) & (v <= hi)), name


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(content=st.binary(max_size=600), suffix=st.sampled_from([".asc", ".blf", ".csv", ".log", ".trc", ".mf4"]),
       prefix=st.sampled_from([b"", b"LOGG", b"MDF     4.10    ", b"date Mon Jan 1 00:00:00 2024\nbase hex\n",
                               b"timestamp,arbitration_id,extended,remote,error,dlc,data\n"]))
def test_any_log_file_reads_or_fails_in_one_line(tmp_path: Path, content: bytes, suffix: str, prefix: bytes) -> None:
    path = tmp_path / f"log{suffix}"
    path.write_bytes(prefix + content)
    try:
        n = check_can_log(path, (".asc", ".blf", ".csv", ".log", ".trc", ".mf4"))
    except InputFileError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc), str(exc)
        return
    assert n > 0
