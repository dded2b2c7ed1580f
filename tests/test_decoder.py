"""FrameDecoder: real cantools decoding of the shipped DBC; every bad input counted, never raised."""

from __future__ import annotations

import math
import random
from pathlib import Path

import can
import cantools
import numpy as np
import pytest

from replay.faults import FaultInjector, FaultSpec
from replay.pack import FrameBuilder
from service.bus.decoder import REJECT_REASONS, FrameDecoder
from service.config import build_config, load_config

ROOT = Path(__file__).resolve().parent.parent
N = 12  # cells: 3 voltage frames, 3 temperature sensors (1 frame), 1 current frame per sample


@pytest.fixture
def cfg():
    return build_config({"pack": {"n_cells": N}, "mapping": {"stale_after_s": 2.0}})


def pack_values(k: int):
    volts = 3.6 + 0.01 * np.arange(N) + 0.001 * k
    temps = np.array([20.0, 25.0, 30.0])
    return volts, temps


def stream(cfg, n_samples=10, dt=0.1, current=lambda k: 10.0 + k, t0=0.0):
    """Frames of ``n_samples`` samples: per sample 3 voltage + 1 temperature + 1 current frame."""
    b = FrameBuilder(cfg)
    out = []
    for k in range(n_samples):
        v, t = pack_values(k)
        out += b.frames_for_sample(t0 + k * dt, current(k), v, t)
    return out


def feed_all(dec, frames):
    samples = []
    for f in frames:
        samples += dec.feed(f)
    return samples


def test_clean_stream(cfg):
    frames = stream(cfg)
    assert len(frames) == 50
    dec = FrameDecoder(cfg)
    samples = feed_all(dec, frames)
    assert len(samples) == 10
    s = samples[-1]
    assert s.t_s == pytest.approx(0.9)
    # the BMS sends positive = charge; current_sign = -1 turns it into positive = discharge
    assert s.current_a == pytest.approx(19.0, abs=0.025)
    v, t = pack_values(9)
    assert np.allclose(s.voltage_v, v, atol=0.0006)
    assert np.allclose(s.temperature_c, np.repeat(t, 4), atol=0.051)
    assert s.fresh.all()
    assert dec.counters["frames_in"] == 50 and dec.counters["frames_decoded"] == 50
    assert dec.rejected == 0 and dec.counters["counter_jump"] == 0
    raw = cfg.input_db().get_message_by_name("BMS_PackStatus").decode(bytes(frames[4].data))
    assert raw["BMS_PackCurrent"] == pytest.approx(-10.0)


def test_first_sample_before_voltages_is_not_fresh(cfg):
    frames = stream(cfg, 2)
    dec = FrameDecoder(cfg)
    (s,) = dec.feed(frames[4])  # current only
    assert not s.fresh.any() and np.isnan(s.voltage_v).all()


def test_unknown_id_and_bad_dlc(cfg):
    dec = FrameDecoder(cfg)
    assert dec.feed(can.Message(arbitration_id=0x555, data=b"\x00" * 8)) == []
    assert dec.feed(can.Message(arbitration_id=0x100, is_extended_id=True, data=b"\x00" * 8)) == []
    f = stream(cfg, 1)[4]
    short = can.Message(timestamp=f.timestamp, arbitration_id=f.arbitration_id, is_extended_id=False,
                        data=bytes(f.data)[:5])
    assert dec.feed(short) == []
    assert dec.counters["unknown_id"] == 2 and dec.counters["bad_dlc"] == 1
    assert dec.feed(can.Message(arbitration_id=0x100, is_extended_id=False, is_error_frame=True)) == []
    assert dec.counters["error_frame"] == 1


def test_decode_error_unknown_mux(cfg):
    dec = FrameDecoder(cfg)
    data = bytearray(stream(cfg, 1)[0].data)
    data[0] = 200  # no block 200 in the DBC
    assert dec.feed(can.Message(arbitration_id=0x110, is_extended_id=False, data=data)) == []
    assert dec.counters["decode_error"] == 1


def test_out_of_range_invalidates_only_that_cell(cfg):
    frames = stream(cfg, 3)
    dec = FrameDecoder(cfg)
    feed_all(dec, frames[:10])
    m = cfg.input_db().get_message_by_name("BMS_CellVoltages")
    bad = m.encode({"BMS_CellVoltMux": 0, "BMS_CellVoltCounter": 2, "BMS_Cell001_V": 7.5,
                    "BMS_Cell002_V": 3.6, "BMS_Cell003_V": 3.6, "BMS_Cell004_V": 3.6})
    feed_all(dec, [can.Message(timestamp=0.2, arbitration_id=0x110, is_extended_id=False, data=bad)])
    (s,) = dec.feed(frames[14])
    assert dec.counters["out_of_range"] == 1
    assert not s.fresh[0] and math.isnan(s.voltage_v[0]) and s.fresh[1:].all()
    # the next valid value makes it fresh again
    (s,) = feed_all(dec, stream(cfg, 1, t0=0.3))
    assert s.fresh.all()


def test_current_out_of_range_emits_no_sample(cfg):
    dec = FrameDecoder(cfg)
    m = cfg.input_db().get_message_by_name("BMS_PackStatus")
    data = m.encode({"BMS_PackCurrent": 1500.0, "BMS_PackVoltage": 40, "BMS_PackCounter": 0})
    assert dec.feed(can.Message(timestamp=1.0, arbitration_id=0x100, is_extended_id=False, data=data)) == []
    assert dec.counters["out_of_range"] == 1


def test_counter_jump_counted_frame_used(cfg):
    frames = [f for f in stream(cfg, 4) if f.arbitration_id == 0x100]
    dec = FrameDecoder(cfg)
    samples = feed_all(dec, [frames[0], frames[2], frames[3]])  # counter 0, 2, 3
    assert len(samples) == 3
    assert dec.counters["counter_jump"] == 1
    assert dec.rejected == 0


def test_timestamp_backwards_and_duplicate(cfg):
    frames = [f for f in stream(cfg, 3) if f.arbitration_id == 0x100]
    dec = FrameDecoder(cfg)
    assert len(dec.feed(frames[1])) == 1
    assert dec.feed(frames[1]) == []  # same bytes again
    assert dec.feed(frames[0]) == []  # older than the last accepted one
    assert dec.counters["duplicate"] == 1 and dec.counters["timestamp_backwards"] == 1
    assert len(dec.feed(frames[2])) == 1


def test_stale_after_timeout(cfg):
    """Voltage block 1 (cells 4-7) stops; its cells go stale after stale_after_s, others stay fresh."""
    frames = stream(cfg, 40, dt=0.1)
    kept = [f for f in frames if not (f.arbitration_id == 0x110 and f.data[0] == 1 and f.timestamp > 0.5)]
    samples = feed_all(FrameDecoder(cfg), kept)
    by_t = {round(s.t_s, 1): s for s in samples}
    assert by_t[2.5].fresh.all()  # 2.0 s after the last block-1 frame: still within the limit
    late = by_t[3.0]
    assert not late.fresh[4:8].any() and late.fresh[:4].all() and late.fresh[8:].all()
    # temperature stale: the sensor's cells go stale
    kept = [f for f in frames if not (f.arbitration_id == 0x120 and f.timestamp > 0.5)]
    last = feed_all(FrameDecoder(cfg), kept)[-1]
    assert not last.fresh.any()


def test_nan_from_float_signal():
    dbc = """VERSION ""
BS_:
BU_: BMS
BO_ 2147484416 Pack: 8 BMS
 SG_ I : 0|32@1- (1,0) [-1000|1000] "A" Vector__XXX
 SG_ V1 : 32|16@1+ (0.001,0) [0|65.535] "V" Vector__XXX
 SG_ T1 : 48|8@1- (1,0) [-128|127] "degC" Vector__XXX
SIG_VALTYPE_ 2147484416 I : 1;
"""
    db = cantools.database.load_string(dbc, "dbc")
    msg = db.get_message_by_name("Pack")
    assert msg.is_extended_frame and msg.frame_id == 0x300  # an extended ID <= 0x7FF
    cfg = build_config({"mapping": {"current_signal": "I", "current_sign": 1.0, "cell_voltage_signals": ["V1"],
                                    "temperature_signals": [{"signal": "T1", "cells": [0]}], "counter_signals": {}}})
    dec = FrameDecoder(cfg, db)
    ok = msg.encode({"I": 2.5, "V1": 3.7, "T1": 25})
    (s,) = dec.feed(can.Message(timestamp=1.0, arbitration_id=0x300, is_extended_id=True, data=ok))
    assert s.current_a == 2.5 and s.fresh.all()
    for i, bad in enumerate((math.nan, math.inf)):
        data = msg.encode({"I": bad, "V1": 3.7, "T1": 25}, strict=False)
        assert dec.feed(can.Message(timestamp=2.0 + i, arbitration_id=0x300, is_extended_id=True, data=data)) == []
    assert dec.counters["nan"] == 2
    # the standard-ID twin of the extended frame is a different frame
    assert dec.feed(can.Message(timestamp=5.0, arbitration_id=0x300, is_extended_id=False, data=ok)) == []
    assert dec.counters["unknown_id"] == 1


def test_fuzz_never_raises(cfg):
    rng = random.Random(3)
    dec = FrameDecoder(cfg)
    ids = [0x100, 0x110, 0x120, 0x7FF, 0x18FF50E5]
    for k in range(3000):
        n = rng.choice([0, 1, 7, 8, 8, 8, 12])
        m = can.Message(timestamp=rng.uniform(0, 10), arbitration_id=rng.choice(ids),
                        is_extended_id=rng.random() < 0.1, data=bytes(rng.getrandbits(8) for _ in range(n)),
                        is_fd=n > 8)
        for s in dec.feed(m):
            ok = s.fresh
            assert np.all((s.voltage_v[ok] >= 1.5) & (s.voltage_v[ok] <= 4.8))
    assert dec.counters["frames_in"] == 3000
    assert dec.stats()["rejected"] == sum(dec.counters[r] for r in REJECT_REASONS) > 0


# -- each replay fault is counted by the right reason -----------------------------------
def test_fault_duplicate(cfg):
    inj = FaultInjector(FaultSpec(duplicate=0.2, seed=1))
    dec = FrameDecoder(cfg)
    feed_all(dec, inj.apply(stream(cfg, 50)))
    assert inj.counts["duplicated"] > 10
    assert dec.counters["duplicate"] == inj.counts["duplicated"]
    assert dec.counters["counter_jump"] == 0


def test_fault_reorder(cfg):
    only_current = [f for f in stream(cfg, 200) if f.arbitration_id == 0x100]
    inj = FaultInjector(FaultSpec(reorder=0.1, seed=2))
    dec = FrameDecoder(cfg)
    feed_all(dec, inj.apply(only_current))
    assert inj.counts["reordered"] > 5
    assert dec.counters["timestamp_backwards"] == inj.counts["reordered"]
    assert dec.counters["counter_jump"] >= inj.counts["reordered"]


def test_fault_drop_goes_stale(cfg):
    inj = FaultInjector(FaultSpec(drop=0.5, seed=3))
    dec = FrameDecoder(cfg)
    samples = feed_all(dec, inj.apply(stream(cfg, 100, dt=1.0)))
    assert inj.counts["dropped"] > 100
    assert dec.counters["counter_jump"] > 0
    assert any(not s.fresh.all() for s in samples) and any(s.fresh.all() for s in samples)
    assert dec.rejected == 0


def test_fault_corrupt_dlc_and_bits(cfg):
    inj = FaultInjector(FaultSpec(corrupt=0.2, corrupt_mode="dlc", seed=4))
    dec = FrameDecoder(cfg)
    feed_all(dec, inj.apply(stream(cfg, 50)))
    assert dec.counters["bad_dlc"] == inj.counts["corrupted_dlc"] > 10
    inj = FaultInjector(FaultSpec(corrupt=0.3, corrupt_mode="bitflip", seed=5))
    dec = FrameDecoder(cfg)
    samples = feed_all(dec, inj.apply(stream(cfg, 200)))
    flipped = inj.counts["corrupted_bitflip"]
    seen = dec.counters["decode_error"] + dec.counters["out_of_range"] + dec.counters["counter_jump"]
    assert flipped > 50 and seen > 0
    for s in samples:
        assert np.all((s.voltage_v[s.fresh] >= 1.5) & (s.voltage_v[s.fresh] <= 4.8))


def test_fault_jitter_keeps_order(cfg):
    inj = FaultInjector(FaultSpec(jitter_s=0.05, seed=6))
    dec = FrameDecoder(cfg)
    samples = feed_all(dec, inj.apply(stream(cfg, 50)))
    assert len(samples) == 50 and dec.rejected == 0
    dts = np.diff([s.t_s for s in samples])
    assert (dts >= 0).all() and dts.std() > 0.005


def test_fault_stuck_cell_and_gap(cfg):
    inj = FaultInjector(FaultSpec(stuck_cells=[(5, 2.0)], bus_gaps=[(4.0, 1.0)], seed=7), config=cfg)
    samples = feed_all(FrameDecoder(cfg), inj.apply(stream(cfg, 80, dt=0.1)))
    assert inj.counts["stuck"] > 0 and inj.counts["gap_dropped"] == 50
    ts = np.array([s.t_s for s in samples])
    assert not ((ts >= 4.0) & (ts < 5.0)).any()
    late = [s for s in samples if s.t_s > 2.05]
    assert len({round(s.voltage_v[5], 4) for s in late}) == 1  # frozen
    assert len({round(s.voltage_v[4], 4) for s in late}) > 5  # neighbours move


def test_user_dbc_via_mapping_only():
    cfg = load_config(ROOT / "configs" / "user_dbc_example" / "acme.toml", check_files=False)
    b = FrameBuilder(cfg)
    dec = FrameDecoder(cfg)
    volts = 3.5 + 0.01 * np.arange(12)
    samples = []
    for k in range(3):
        samples += feed_all(dec, b.frames_for_sample(k * 0.05, -4.0, volts, np.array([10.0, 11.0, 12.0])))
    s = samples[-1]
    assert len(samples) == 3 and s.fresh.all()
    assert s.current_a == pytest.approx(-4.0)  # ACME sends positive = discharge already
    assert np.allclose(s.voltage_v, volts, atol=1e-4)
    assert list(s.temperature_c) == [10.0] * 5 + [11.0] * 5 + [12.0] * 2
    assert dec.rejected == 0 and dec.counters["counter_jump"] == 0
