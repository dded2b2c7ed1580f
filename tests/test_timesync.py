"""Time sync (issue 28, item 4): a replay at speed onto a bus that stamps frames on arrival.

A kernel bus (vcan0, can0) stamps every frame when it arrives, so a replay at 20x hands the
daemon time steps 20x too short.  With ``mapping.time_signal`` the replay puts each sample's
time in ``BMS_TimeSync`` and the daemon clocks samples by it.  Real cantools decoding of the
shipped DBC, real python-can virtual buses, the real daemon and estimator on the bundled
Panasonic 18650PF US06 drive.  The same run over a real vcan0 is in ``test_vcan_e2e.py``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import can
import numpy as np
import pytest
from daemon_support import run_daemon

from replay.pack import FrameBuilder, SpreadSpec, pack_frames
from service.bus.decoder import FRAME_ACCEPTS, REANCHOR_AFTER, REJECT_REASONS, FrameDecoder
from service.bus.timesync import TimeSignal, TimeSignalError
from service.cell.profile import load_profile
from service.config import (
    DEFAULT_CELL_PROFILE,
    DEFAULT_INPUT_DBC,
    DEFAULT_OUTPUT_DBC,
    ConfigError,
    build_config,
    check_input_mapping,
    load_config,
)
from service.recording import load_recording

ROOT = Path(__file__).resolve().parents[1]
RECORDING = ROOT / "service" / "data" / "pan18650pf_25C_US06.csv"  # bundled: always present
N = 12  # decoder tests: 1 time-sync, 3 voltage, 1 temperature, 1 current frame per sample
SYNC_ID, CURRENT_ID = 0x0F0, 0x100
SPEED = 20.0
#: what a kernel bus adds between two frames' arrival stamps in one burst (a few µs)
FRAME_GAP_S = 20e-6


def identity_holds(c) -> bool:
    return c["frames_in"] == sum(c[k] for k in FRAME_ACCEPTS) + sum(c[r] for r in REJECT_REASONS)


def config(n: int = N, time_signal: str | None = "BMS_SampleTime", **extra):
    raw = {"pack": {"n_cells": n}, **extra}
    if time_signal is not None:
        raw["mapping"] = {"time_signal": time_signal}
    return build_config(raw)


@pytest.fixture
def cfg():
    return config()


def stream(cfg, n_samples: int, dt: float = 0.1, t0: float = 100.0) -> list[can.Message]:
    b = FrameBuilder(cfg)
    out: list[can.Message] = []
    for k in range(n_samples):
        v = 3.6 + 0.01 * np.arange(cfg.pack.n_cells) + 0.001 * k
        out += b.frames_for_sample(t0 + k * dt, 10.0, v, np.full(len(cfg.mapping.temperature_signals), 25.0))
    return out


def kernel_stamped(frames: list[can.Message], speed: float = SPEED, wall0: float = 1.7e9) -> list[can.Message]:
    """The frames as a kernel bus hands them over when a replay at ``speed`` sends them:
    stamped with arrival wall time, the recording's time steps divided by ``speed``."""
    t0 = frames[0].timestamp
    return [can.Message(timestamp=wall0 + (f.timestamp - t0) / speed + k * FRAME_GAP_S,
                        arbitration_id=f.arbitration_id, is_extended_id=f.is_extended_id, data=f.data)
            for k, f in enumerate(frames)]


def with_sync_time(db, msg: can.Message, t_s: float) -> can.Message:
    """A copy of a time-sync frame carrying ``t_s`` instead (raw, so out-of-period values fit too)."""
    m = db.get_message_by_frame_id(SYNC_ID)
    raw = round(t_s * 1000) & 0xFFFFFFFF
    return can.Message(timestamp=msg.timestamp, arbitration_id=SYNC_ID, is_extended_id=False,
                       data=m.encode({"BMS_SampleTime": raw}, scaling=False))


def feed(dec: FrameDecoder, frames) -> list:
    out = []
    for f in frames:
        out += dec.feed(f)
    return out


# -- the signal, the config and the replay ----------------------------------------------------
def test_time_signal_wraps_after_2_to_the_32_ms_and_unwraps_to_a_continuous_clock() -> None:
    db = config().input_db()
    ts = TimeSignal.find(db, "BMS_SampleTime")
    assert ts.period_s == pytest.approx(2**32 / 1000) and ts.period_s / 86400 > 49
    assert ts.wire_value(12.3456) == 12.346  # 1 ms resolution
    assert ts.wire_value(ts.period_s + 1.5) == 1.5
    assert ts.unwrap(1.5, near_s=ts.period_s - 0.5) == pytest.approx(ts.period_s + 1.5)
    assert ts.unwrap(ts.period_s - 0.5, near_s=ts.period_s + 1.5) == pytest.approx(ts.period_s - 0.5)
    with pytest.raises(TimeSignalError, match="multiplexed"):
        TimeSignal.find(db, "BMS_Cell001_V")
    with pytest.raises(TimeSignalError, match="not in the DBC"):
        TimeSignal.find(db, "BMS_NoSuchTime")
    # a replay across the wrap: the decoder's samples keep the recording's steps
    cfg = config()
    frames = stream(cfg, 40, dt=0.1, t0=ts.period_s - 2.0)
    samples = feed(FrameDecoder(cfg), frames)
    assert len(samples) == 40
    assert np.allclose(np.diff([s.t_s for s in samples]), 0.1, atol=1.5e-3)
    assert samples[-1].t_s > ts.period_s  # past the wrap, on the same clock


def test_replay_sends_the_time_first_in_every_sample_only_when_mapped() -> None:
    rec = load_recording(RECORDING).slice(0, 50)
    profile = load_profile(DEFAULT_CELL_PROFILE)
    frames, pack = pack_frames(rec, config(8), profile, 8, time_offset_s=1000.0)
    db = config(8).input_db()
    per_sample = len(frames) // len(pack)
    assert per_sample == 5  # time sync, 2 voltage blocks, 1 temperature, 1 current
    for k in range(len(pack)):
        first, *rest = frames[k * per_sample:(k + 1) * per_sample]
        assert first.arbitration_id == SYNC_ID and SYNC_ID not in {f.arbitration_id for f in rest}
        t = db.get_message_by_frame_id(SYNC_ID).decode(first.data)["BMS_SampleTime"]
        assert t == pytest.approx(pack.time_s[k], abs=5e-4) and rest[-1].arbitration_id == CURRENT_ID
    plain, _ = pack_frames(rec, config(8, time_signal=None), profile, 8)
    assert len(plain) == 4 * len(pack) and SYNC_ID not in {f.arbitration_id for f in plain}


def test_config_names_the_time_signal_and_check_validates_it(tmp_path: Path) -> None:
    assert build_config({}).mapping.time_signal is None  # a user's DBC without one works as before
    for name in ("default.toml", "vcan0.toml"):
        assert load_config(ROOT / "configs" / name).mapping.time_signal == "BMS_SampleTime"
    assert load_config(ROOT / "configs" / "socketcan_can0.toml").mapping.time_signal is None
    with pytest.raises(ConfigError, match=r"mapping\.time_signal: signal 'BMS_SampleTme' not in dbc.input.*"
                                          r"did you mean 'BMS_SampleTime'"):
        check_input_mapping(config(time_signal="BMS_SampleTme"))
    with pytest.raises(ConfigError, match=r"mapping\.time_signal: .*multiplexed"):
        check_input_mapping(config(8, time_signal="BMS_Temp24_C"))  # sensor 24 covers none of 8 cells
    with pytest.raises(ConfigError, match=r"mapping\.time_signal: signal 'BMS_PackCurrent' is already mapped"):
        config(time_signal="BMS_PackCurrent")
    # and as `socd check` reports it
    from service.commands.check import check_config

    cfg = tmp_path / "c.toml"
    cfg.write_text(f'cell_profile = "{DEFAULT_CELL_PROFILE}"\n[dbc]\ninput = "{DEFAULT_INPUT_DBC}"\n'
                   f'output = "{DEFAULT_OUTPUT_DBC}"\n[mapping]\ntime_signal = "BMS_Sampletime"\n')
    res = check_config(str(cfg))
    assert not res.ok and any("mapping.time_signal" in p and "BMS_SampleTime" in p for p in res.problems), res.problems
    good = load_config(ROOT / "configs" / "vcan0.toml")
    assert good.mapping.time_signal and check_config(str(ROOT / "configs" / "vcan0.toml")).ok


# -- the decoder: sample time from the sync frame ----------------------------------------------
def test_kernel_stamped_fast_replay_keeps_the_recording_time_steps(cfg) -> None:
    frames = stream(cfg, 300, dt=0.1)
    fast = kernel_stamped(frames)
    dec = FrameDecoder(cfg)
    samples = feed(dec, fast)
    assert len(samples) == 300 and all(s.fresh.all() for s in samples[1:])
    assert np.allclose([s.t_s for s in samples], 100.0 + 0.1 * np.arange(300), atol=5e-4)
    assert dec.counters["frames_decoded"] == len(fast) and identity_holds(dec.counters)
    # the control: without the time signal the same frames give 20x shorter steps
    plain = config(time_signal=None)
    no_sync = [f for f in fast if f.arbitration_id != SYNC_ID]
    steps = np.diff([s.t_s for s in feed(FrameDecoder(plain), no_sync)])
    assert np.allclose(steps, 0.1 / SPEED, rtol=0.05)  # (plus the frames' arrival gaps)


def test_frames_before_the_first_time_and_repeats_are_counted_once(cfg) -> None:
    frames = stream(cfg, 50)
    dec = FrameDecoder(cfg)
    # joined mid-sample: the frames before the first time sync have no time
    samples = feed(dec, frames[2:8])
    assert dec.counters["no_time_sync"] == 4 and samples == []
    dup = frames[12]  # sample 2's time-sync frame, sent twice
    assert dup.arbitration_id == SYNC_ID
    samples += feed(dec, frames[8:13] + [dup] + frames[13:])
    assert dec.counters["duplicate"] == 1 and len(samples) == 49
    assert dec.rejected == 5 and identity_holds(dec.counters)
    # wild arrival stamps on the other frames do not matter: their time is the sync's
    dec2 = FrameDecoder(cfg)
    wild = [f if f.arbitration_id == SYNC_ID else can.Message(
        timestamp=w, arbitration_id=f.arbitration_id, is_extended_id=False, data=f.data)
        for f, w in zip(frames, [math.nan, -1e6, 1e308, 0.0] * len(frames))]
    got = feed(dec2, wild)
    assert [s.t_s for s in got] == pytest.approx([s.t_s for s in feed(FrameDecoder(cfg), frames)])
    assert dec2.rejected == 0


def test_a_lost_time_frame_costs_only_its_sample(cfg) -> None:
    frames = stream(cfg, 100)
    lost = 6 * 40  # sample 40's time-sync frame
    assert frames[lost].arbitration_id == SYNC_ID
    dec = FrameDecoder(cfg)
    samples = feed(dec, frames[:lost] + frames[lost + 1:])
    assert len(samples) == 99 and dec.counters["time_sync_missing"] == 1
    assert all(abs(s.t_s - 104.0) > 1e-6 for s in samples)  # no sample at a time it did not have
    assert identity_holds(dec.counters)


@pytest.mark.parametrize("bad_t", [1e6, 100.0 + 1e6, 50.0, 0.0, 4294967.295])
def test_one_bad_sync_time_costs_only_its_sample(cfg, bad_t: float) -> None:
    frames = stream(cfg, 200)
    k = 6 * 60  # sample 60's time-sync frame
    db = cfg.input_db()
    bad = with_sync_time(db, frames[k], bad_t)
    dec = FrameDecoder(cfg)
    samples = feed(dec, frames[:k] + [bad] + frames[k + 1:])
    assert len(samples) == 199 and dec.counters["time_sync_missing"] == 1
    assert dec.counters["timestamp_jump"] + dec.counters["timestamp_backwards"] == 1
    assert dec.counters["clock_reanchor"] == 0 and not any(s.reanchored for s in samples)
    assert identity_holds(dec.counters)


@pytest.mark.parametrize("jump_s", [1e6, -5e4, 60.0])
def test_a_genuine_jump_of_the_sync_clock_reanchors(cfg, jump_s: float) -> None:
    frames = stream(cfg, 300)
    db = cfg.input_db()
    moved = [with_sync_time(db, f, 100.0 + (i // 6) * 0.1 + jump_s) if f.arbitration_id == SYNC_ID else f
             for i, f in enumerate(frames) if i >= 6 * 100]  # the sender's clock moved at sample 100
    dec = FrameDecoder(cfg)
    samples = feed(dec, frames[:600] + moved)
    assert dec.counters["clock_reanchor"] == 1
    assert dec.counters["timestamp_jump"] + dec.counters["timestamp_backwards"] == REANCHOR_AFTER - 1
    assert dec.counters["time_sync_missing"] == REANCHOR_AFTER - 1  # those frames' samples had no time
    assert len(samples) == 300 - (REANCHOR_AFTER - 1)
    marked = [s for s in samples if s.reanchored]
    assert len(marked) == 1 and marked[0].t_s == pytest.approx(110.0 + 0.1 * (REANCHOR_AFTER - 1) + jump_s)
    assert identity_holds(dec.counters)


@pytest.mark.parametrize("ahead_s", [0.35, 1.0, 9.9])
def test_a_sync_time_a_little_ahead_is_rolled_back(cfg, ahead_s: float) -> None:
    frames = stream(cfg, 200)
    k = 6 * 60
    db = cfg.input_db()
    bad = with_sync_time(db, frames[k], 106.0 + ahead_s)
    dec = FrameDecoder(cfg)
    samples = feed(dec, frames[:k] + [bad] + frames[k + 1:])
    assert dec.counters["timestamp_rollback"] == 1 and dec.counters["clock_reanchor"] == 0
    good = {round(100.0 + 0.1 * i, 3) for i in range(200)}
    assert len({round(s.t_s, 3) for s in samples} & good) == 199  # all but the bad one's own sample
    assert sum(s.reanchored for s in samples) == 1 and identity_holds(dec.counters)


# -- the daemon: the same SOC from an in-process replay and a kernel-stamped 20x replay -------------
def daemon_config(tmp_path: Path, time_signal: str | None, tag: str):
    """The daemon's config for one run, with both identifiers on (the slow one is off by
    default): it is clocked by sample time, so a run is the same at any replay speed."""
    return build_config({
        "cell_profile": str(DEFAULT_CELL_PROFILE),
        "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": 8},
        "mapping": {"time_signal": time_signal},
        "bus": {"interface": "virtual", "channel": f"timesync-{tag}-{time.monotonic_ns()}"},
        "output": {"zenoh_enabled": False, "can_enabled": False},
        "estimator": {"slow_identifier": True},
        "checkpoint": {"path": str(tmp_path / f"{tag}.ckpt")},
    })


@pytest.fixture(scope="module")
def drive():
    rec = load_recording(RECORDING).slice(0, 750)  # 12.5 minutes of US06 from full charge
    profile = load_profile(DEFAULT_CELL_PROFILE)
    cfg = config(8)
    frames, pack = pack_frames(rec, cfg, profile, 8, SpreadSpec(soc=0.02, capacity=0.02), seed=5, start_soc=1.0)
    return frames, pack


def test_kernel_stamped_20x_replay_gives_the_in_process_soc(tmp_path: Path, drive) -> None:
    frames, pack = drive
    no_sync = [f for f in frames if f.arbitration_id != SYNC_ID]
    # in process (python-can's virtual bus keeps the sender's stamps): today's reference
    ref = run_daemon(daemon_config(tmp_path, None, "ref"), no_sync)
    # a kernel bus at 20x: arrival stamps, the recording's time only in BMS_TimeSync
    fast = run_daemon(daemon_config(tmp_path, "BMS_SampleTime", "sync"), kernel_stamped(frames))
    assert ref.steps == fast.steps == len(pack) - 1
    c = {**fast.decoder.stats(), **fast.counters()}
    assert c["frames_in"] == len(frames) and c["frames_rejected"] == 0 and c["time_sync_missing"] == 0
    moved = float(np.min(pack.truth_soc[0] - pack.truth_soc[-1]))
    assert moved > 0.1, "the drive moved the SOC too little to tell time steps apart"
    diff_pct = 100 * np.max(np.abs(fast.estimator.soc - ref.estimator.soc))
    print(f"\nSOC, kernel-stamped {SPEED:g}x replay with time sync vs in-process: max |diff| {diff_pct:.2e} %")
    assert diff_pct < 0.1
    # the control: the same kernel stamps without time sync are far off (the test can fail)
    blind = run_daemon(daemon_config(tmp_path, None, "blind"), kernel_stamped(no_sync))
    blind_pct = 100 * np.max(np.abs(blind.estimator.soc - ref.estimator.soc))
    print(f"SOC, the same without time sync: max |diff| {blind_pct:.2f} %")
    assert blind_pct > 1.0
