"""OutputEncoder + decode_output: every output frame round-trips; bad values are clamped, never raised."""

from __future__ import annotations

import can
import numpy as np
import pytest

from service.bus.encoder import OutputEncoder, decode_output, flag_signal
from service.bus.types import STATUS_FLAGS, PackSnapshot
from service.config import build_config

N = 96


def snapshot(n=N, **kw):
    base = dict(
        t_s=100.0,
        soc=np.linspace(0.2, 0.8, n),
        soc_std=np.full(n, 0.012),
        voltage_v=np.full(n, 3.7),
        params={"r_ohm": np.full(n, 0.021), "r_ct": np.full(n, 0.0153), "c_dl": np.full(n, 800.0),
                "m": np.full(n, 0.72), "r_df": np.full(n, 0.0307), "c_df": np.full(n, 9000.0),
                "n": np.full(n, 0.55)},
        stale=np.zeros(n, bool),
        status_flags={"ocv_init": True, "zenoh_down": False, "publish_drops": True},
        counters={"frames_rejected": 42},
    )
    base.update(kw)
    return PackSnapshot(**base)


@pytest.fixture(scope="module")
def enc():
    return OutputEncoder(build_config({}))


def by_message(frames):
    out = {}
    for f in frames:
        d = decode_output(f)
        out.setdefault(d["message"], []).append(d)
    return out


def test_frames_and_roundtrip(enc):
    frames = enc.encode(snapshot())
    assert len(frames) == 2 * N + 3
    assert all(f.is_extended_id and f.arbitration_id > 0x7FF and len(f.data) <= 8 for f in frames)
    assert all(f.timestamp == 100.0 for f in frames)
    d = by_message(frames)
    socs = d["SOCD_CellSoc"]
    assert [s["SOCD_SocCellIndex"] for s in socs] == list(range(N))
    assert np.allclose([s["SOCD_Soc"] for s in socs], np.linspace(20, 80, N), atol=0.006)
    assert all(s["SOCD_SocStd"] == pytest.approx(1.2) and s["SOCD_SocStale"] == 0 for s in socs)
    p = d["SOCD_CellParams"][7]
    assert p["SOCD_ParCellIndex"] == 7
    assert p["SOCD_ROhm"] == pytest.approx(21.0, abs=0.05)
    assert p["SOCD_RCt"] == pytest.approx(15.3, abs=0.05)
    assert p["SOCD_RDf"] == pytest.approx(30.7, abs=0.05)
    assert p["SOCD_M"] == pytest.approx(0.72, abs=0.002) and p["SOCD_N"] == pytest.approx(0.55, abs=0.0021)
    (summ,) = d["SOCD_PackSummary"]
    assert summ["SOCD_SocMin"] == pytest.approx(20.0) and summ["SOCD_SocMax"] == pytest.approx(80.0)
    assert summ["SOCD_SocMean"] == pytest.approx(50.0, abs=0.01)
    assert summ["SOCD_SocMinCell"] == 0 and summ["SOCD_SocMaxCell"] == N - 1
    (st,) = d["SOCD_Status"]
    assert st["flags"]["ocv_init"] and st["flags"]["publish_drops"] and not st["flags"]["zenoh_down"]
    assert not st["flags"]["stale_cells"]
    assert st["SOCD_FramesRejected"] == 42 and st["SOCD_StaleCells"] == 0
    assert set(st["flags"]) == set(STATUS_FLAGS)


def test_status_word_is_the_flag_bits(enc):
    flags = {f: (i % 3 == 0) for i, f in enumerate(STATUS_FLAGS)}
    (status,) = [f for f in enc.encode(snapshot(status_flags=flags)) if decode_output(f)["message"] == "SOCD_Status"]
    word = int.from_bytes(bytes(status.data[:4]), "little")
    expected = sum(1 << i for i, f in enumerate(STATUS_FLAGS) if flags[f])
    assert word == expected
    assert flag_signal("stale_cells") == "SOCD_FlagStaleCells"


def test_rolling_counters(enc):
    e = OutputEncoder(build_config({}))
    counters = [decode_output(f)["SOCD_StatusCounter"] for _ in range(20)
                for f in e.encode(snapshot(n=2)) if f.arbitration_id == 0x18FF53E5]
    assert counters == [k % 16 for k in range(20)]


def test_clamping_and_stale(enc):
    n = 6
    soc = np.array([1.5, -0.2, np.nan, 0.5, 0.4, np.inf])
    stale = np.array([False, False, False, True, False, False])
    snap = snapshot(n=n, soc=soc, soc_std=np.array([2.0, 0.01, np.nan, 0.01, -1, 0.01]), stale=stale,
                    params={"r_ohm": np.full(n, 5.0), "m": np.full(n, -1.0)}, status_flags={})
    d = by_message(enc.encode(snap))
    socs = d["SOCD_CellSoc"]
    assert [s["SOCD_Soc"] for s in socs] == [100.0, 0.0, 0.0, 50.0, 40.0, 100.0]
    assert [s["SOCD_SocStale"] for s in socs] == [0, 0, 1, 1, 0, 1]  # NaN/inf SOC is flagged
    assert socs[0]["SOCD_SocStd"] == 100.0 and socs[4]["SOCD_SocStd"] == 0.0
    p = d["SOCD_CellParams"][0]
    assert p["SOCD_ROhm"] == pytest.approx(409.5) and p["SOCD_M"] == 0.0 and p["SOCD_RCt"] == 0.0
    (summ,) = d["SOCD_PackSummary"]  # stale and NaN cells are left out
    assert summ["SOCD_SocMaxCell"] == 0 and summ["SOCD_SocMinCell"] == 1
    (st,) = d["SOCD_Status"]
    assert st["flags"]["stale_cells"] and st["SOCD_StaleCells"] == 1


def test_never_raises_on_garbage(enc):
    bad = PackSnapshot(t_s=float("nan"), soc=np.array(["x"], dtype=object), soc_std=np.zeros(3),
                       voltage_v=np.zeros(1), params={"r_ohm": "nope"}, stale=None,
                       status_flags={"unknown_flag": True}, counters={"frames_rejected": 10**9})
    frames = enc.encode(bad)
    assert isinstance(frames, list)
    frames = enc.encode(snapshot(n=3, params={"r_ohm": np.zeros(7)}, counters={"frames_rejected": 10**9,
                                                                               "stale_cells": -5}))
    st = by_message(frames)["SOCD_Status"][0]
    assert st["SOCD_FramesRejected"] == 65535 and st["SOCD_StaleCells"] == 0
    empty = enc.encode(snapshot(n=0))
    assert [decode_output(f)["message"] for f in empty] == ["SOCD_PackSummary", "SOCD_Status", "SOCD_PackUsable"]


def test_decode_output_ignores_other_frames():
    assert decode_output(can.Message(arbitration_id=0x100, data=b"\0" * 8)) == {}
    assert decode_output(can.Message(arbitration_id=0x18FF50E5, is_extended_id=True, data=b"\0" * 3)) == {}
    assert decode_output(can.Message(arbitration_id=0x18FF50E5, is_extended_id=False, data=b"\0" * 8)) == {}


def test_more_cells_than_output_index_are_cut(enc):
    frames = enc.encode(snapshot(n=300, stale=np.zeros(300, bool)))
    assert len(frames) == 2 * 256 + 3
