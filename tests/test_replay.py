"""socd replay: pack expansion with truth, real python-can virtual buses and log files of every format."""

from __future__ import annotations

import csv
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from replay.faults import FaultSpec
from replay.pack import SpreadSpec, estimate_start_soc, pack_frames
from replay.player import LOG_SUFFIXES, play, read_log
from service.bus.decoder import FrameDecoder
from service.cell.profile import CellProfile
from service.cli import main as socd_main
from service.config import build_config, load_config
from service.recording import load_recording

ROOT = Path(__file__).resolve().parent.parent
DATA = Path("/work/shared/data/real/panasonic_18650pf/pan18650pf_25C_US06.csv")
OCV_TABLE = Path("/work/shared/data/real/ocv/ocv_pan18650pf_25C_soc_table.csv")
N = 8

pytestmark = pytest.mark.skipif(not DATA.is_file() or not OCV_TABLE.is_file(), reason="shared data not present")


def make_profile() -> CellProfile:
    rows = list(csv.DictReader(OCV_TABLE.open()))
    return CellProfile(
        name="test", capacity_ah=2.77,
        ocv={"soc": [float(r["soc"]) for r in rows], "ocv_v": [[float(r["ocv_avg_v"]) for r in rows]]},
        parameters=[{"r_ohm": 0.02, "r_ct": 0.01, "c_dl": 500.0, "m": 0.8, "r_df": 0.02, "c_df": 5000.0, "n": 0.6}],
    )


@pytest.fixture(scope="module")
def profile():
    return make_profile()


@pytest.fixture(scope="module")
def recording():
    return load_recording(DATA).slice(0, 300)  # 5 minutes of US06 at 1 s (rest, then the drive)


@pytest.fixture(scope="module")
def cfg():
    return build_config({"pack": {"n_cells": N}})


@pytest.fixture(scope="module")
def generated(recording, cfg, profile):
    return pack_frames(recording, cfg, profile, N, SpreadSpec(0.02, 0.1, 0.02, 0.5), seed=1)


def decode(cfg, frames):
    dec = FrameDecoder(cfg)
    samples = []
    for f in frames:
        samples += dec.feed(f)
    return dec, samples


def test_pack_expansion(generated, recording):
    frames, pack = generated
    assert len(frames) == len(recording) * 4  # per sample: 2 voltage blocks, 1 temperature, 1 current
    assert pack.truth_soc.shape == (len(recording), N) and pack.voltage_v.shape == (len(recording), N)
    assert 0.9 < pack.soc_ref[0] <= 1.0  # US06 starts from full charge
    assert np.std(pack.truth_soc[0]) > 0.005  # the SOC spread
    dq = np.cumsum(recording.current_a * recording.dt_s()) / 3600.0
    assert np.allclose(pack.soc_ref[0] - pack.soc_ref, dq / 2.77)
    assert np.allclose(pack.truth_soc[0] - pack.truth_soc, dq[:, None] / pack.capacity_ah[None, :])


def test_pack_without_spread_equals_recording(recording, cfg, profile):
    frames, pack = pack_frames(recording, cfg, profile, N)
    assert np.allclose(pack.voltage_v, recording.voltage_v[:, None])
    assert np.allclose(pack.truth_soc, pack.soc_ref[:, None])
    _, samples = decode(cfg, frames)
    assert np.allclose([s.voltage_v for s in samples], pack.voltage_v, atol=0.0006)


def test_seeded(recording, cfg, profile, generated):
    again, _ = pack_frames(recording, cfg, profile, N, SpreadSpec(0.02, 0.1, 0.02, 0.5), seed=1)
    other, _ = pack_frames(recording, cfg, profile, N, SpreadSpec(0.02, 0.1, 0.02, 0.5), seed=2)
    assert [bytes(f.data) for f in again] == [bytes(f.data) for f in generated[0]]
    assert [bytes(f.data) for f in other] != [bytes(f.data) for f in generated[0]]


def test_start_soc_from_rest_and_given(recording, profile, cfg):
    start = estimate_start_soc(recording, profile)
    assert 0.9 < start.soc <= 1.0 and "read from the OCV at" in start.source
    _, pack = pack_frames(recording, cfg, profile, N, start_soc=0.5, time_offset_s=1000.0)
    assert pack.soc_ref[0] == 0.5 and pack.time_s[0] == 1000.0


def test_decoded_frames_match_pack(generated, cfg):
    frames, pack = generated
    dec, samples = decode(cfg, frames)
    assert len(samples) == len(pack) and dec.rejected == 0 and dec.counters["counter_jump"] == 0
    assert np.allclose([s.t_s for s in samples], pack.time_s)
    assert np.allclose([s.current_a for s in samples], pack.current_a, atol=0.026)
    assert np.allclose([s.voltage_v for s in samples], pack.voltage_v, atol=0.0006)
    assert np.allclose([s.temperature_c for s in samples], pack.temperature_c, atol=0.051)
    assert all(s.fresh.all() for s in samples)


def test_play_over_virtual_bus(generated, cfg):
    frames, pack = generated
    chan = "test_replay_virtual"
    with can.Bus(interface="virtual", channel=chan, preserve_timestamps=True) as rx, \
            can.Bus(interface="virtual", channel=chan, preserve_timestamps=True) as tx:
        stats = play(tx, frames, speed=0.0)
        got = []
        while (m := rx.recv(timeout=0.2)) is not None:
            got.append(m)
    assert stats.frames_sent == len(frames) == len(got) and stats.frames_failed == 0
    dec, samples = decode(cfg, got)
    assert len(samples) == len(pack) and dec.rejected == 0
    assert samples[-1].t_s == pytest.approx(pack.time_s[-1])


def test_paced_play_and_stop_event(generated):
    frames = [f for f in generated[0] if f.timestamp < 20.0]  # 20 s of recording
    t0 = time.perf_counter()
    stats = play(None, frames, speed=100.0)
    wall = time.perf_counter() - t0
    assert 0.95 * stats.span_s / 100.0 <= wall < 2.0
    stop = threading.Event()
    threading.Timer(0.1, stop.set).start()
    stats = play(None, generated[0], speed=1.0, stop_event=stop)
    assert stats.stopped and stats.duration_s < 1.0


def test_window_and_loop(generated, cfg):
    frames, pack = generated
    sent: list[can.Message] = []
    stats = play(None, frames, start=10.0, stop=20.0, listeners=[sent.append])
    assert {round(m.timestamp) for m in sent} == set(range(10, 20)) and stats.frames_skipped > 0
    looped = []
    stats = play(None, frames[:40], loop=3, listeners=[looped.append])  # 10 samples a pass
    assert len(looped) == 120 and stats.loops == 3
    dec, samples = decode(cfg, looped)
    assert len(samples) == 30 and dec.counters["timestamp_backwards"] == 0 and dec.counters["duplicate"] == 0
    assert np.all(np.diff([s.t_s for s in samples]) > 0)


@pytest.mark.parametrize("suffix", LOG_SUFFIXES)
def test_log_roundtrip_every_format(suffix, generated, cfg, tmp_path):
    frames, pack = generated
    frames = [f for f in frames if f.timestamp < 60.0]
    path = tmp_path / f"pack{suffix}"
    with can.Logger(path) as logger:
        play(None, frames, listeners=[logger])
    back = list(read_log(path))
    assert len(back) == len(frames)
    assert [(m.arbitration_id, bytes(m.data)) for m in back] == [(f.arbitration_id, bytes(f.data)) for f in frames]
    # and through a bus into the decoder
    chan = f"test_log_{suffix[1:]}"
    with can.Bus(interface="virtual", channel=chan, preserve_timestamps=True) as rx, \
            can.Bus(interface="virtual", channel=chan, preserve_timestamps=True) as tx:
        play(tx, read_log(path), speed=0.0)
        got = []
        while (m := rx.recv(timeout=0.2)) is not None:
            got.append(m)
    dec, samples = decode(cfg, got)
    assert len(samples) == 60 and dec.rejected == 0
    assert np.allclose(np.diff([s.t_s for s in samples]), np.diff(pack.time_s[:60]), atol=1e-3)


def test_faults_in_play_are_reported(generated, cfg):
    frames = generated[0][:500]
    spec = FaultSpec(drop=0.05, duplicate=0.05, corrupt=0.05, corrupt_mode="dlc", seed=9,
                     stuck_cells=[(3, 10.0)], bus_gaps=[(50.0, 5.0)])
    out = []
    stats = play(None, frames, faults=spec, listeners=[out.append], config=cfg)
    f = stats.faults
    assert f["dropped"] > 0 and f["duplicated"] > 0 and f["corrupted_dlc"] > 0 and f["gap_dropped"] > 0
    assert f["stuck"] > 0
    dec, _ = decode(cfg, out)
    # a corrupted frame may also have been duplicated: both copies are bad
    assert f["corrupted_dlc"] <= dec.counters["bad_dlc"] <= f["corrupted_dlc"] + f["duplicated"]
    assert dec.counters["duplicate"] > 0


def test_cli_record_and_truth(tmp_path, profile):
    from service.cell.profile import save_profile

    prof = tmp_path / "cell.toml"
    save_profile(profile, prof)
    out, truth = tmp_path / "out.blf", tmp_path / "truth.csv"
    rc = socd_main(["replay", str(DATA), "--cell", str(prof), "--cells", "4", "--stop", "30",
                    "--spread-soc", "0.02", "--seed", "3", "--record", str(out), "--truth-out", str(truth),
                    "--drop", "0.1", "--quiet"])
    assert rc == 0
    n = len(list(read_log(out)))
    # the default config: 1 time-sync + 1 voltage + 1 temperature + 1 current frame per sample, some dropped
    assert 0 < n < 30 * 4
    rows = list(csv.reader(truth.open()))
    assert rows[0][:5] == ["time_s", "current_a", "soc_ref", "soc_0", "soc_1"] and len(rows[0]) == 7
    # a log file replays onto a bus named by python-can's flags
    rc = socd_main(["replay", str(out), "-i", "virtual", "-c", "cli_test", "--fast", "--quiet"])
    assert rc == 0


def test_log_with_ids_the_dbc_does_not_define_is_warned_about(tmp_path, capsys):
    log = tmp_path / "foreign.asc"
    with can.Logger(str(log)) as logger:
        for k in range(6):
            # 0x123 and the extended 0x18FF0001 are in no frame of the shipped input DBC
            msg_id, ext = ((0x123, False), (0x18FF0001, True))[k % 2]
            logger.on_message_received(can.Message(timestamp=float(k), arbitration_id=msg_id,
                                                   is_extended_id=ext, data=bytes(8)))
    rc = socd_main(["replay", str(log), "-i", "virtual", "-c", "unknown_ids", "--fast", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0
    assert "6 of 6 frames" in err and "0x123 3x" in err and "0x18FF0001 3x" in err
    assert "rejected" in err


def test_log_of_the_dbcs_own_frames_is_not_warned_about(generated, tmp_path, capsys):
    log = tmp_path / "own.asc"
    with can.Logger(str(log)) as logger:
        for msg in generated[0][:50]:
            logger.on_message_received(msg)
    assert socd_main(["replay", str(log), "-i", "virtual", "-c", "own_ids", "--fast", "--quiet"]) == 0
    assert "does not define" not in capsys.readouterr().err


def test_cli_errors(tmp_path):
    assert socd_main(["replay", str(tmp_path / "missing.csv")]) == 2
    bad = tmp_path / "x.txt"
    bad.write_text("hello")
    assert socd_main(["replay", str(bad), "--no-send"]) == 2


def test_user_dbc_replay(recording, profile):
    cfg = load_config(ROOT / "configs" / "user_dbc_example" / "acme.toml", check_files=False)
    frames, pack = pack_frames(recording, cfg, profile, spread=SpreadSpec(soc=0.02), seed=4)
    assert {f.arbitration_id for f in frames} == {0x3A0, 0x3B0, 0x3C0}
    dec, samples = decode(cfg, frames)
    assert len(samples) == len(recording) and dec.rejected == 0
    assert np.allclose([s.voltage_v for s in samples], pack.voltage_v, atol=6e-5)
    assert np.allclose([s.current_a for s in samples], pack.current_a, atol=0.051)


def test_no_generated_cell_starts_above_full(recording, profile):
    from replay.pack import expand_pack

    # the recording opens at rest near full charge: a 5 % SOC spread would put half the
    # cells above 100 % if the start were not bounded
    pack = expand_pack(recording, profile, 64, SpreadSpec(soc=0.05), seed=3, start_soc=0.99)
    assert pack.truth_soc[0].max() <= 1.0
    assert pack.truth_soc[0].min() < 0.97  # the spread is still there below full


def test_truth_out_says_when_its_start_was_read_from_a_voltage_still_relaxing(tmp_path, capsys):
    """A drive that opens under load had its truth placed from the voltage one second into its first
    pause, without a word; with --soc0 nothing is said."""
    from service.cli import main

    rows = "\n".join(f"{t},{1.0 if t % 20 < 10 else 0.0},{3.9 - 0.001 * t},25.0" for t in range(120))
    rec = tmp_path / "drive.csv"
    rec.write_text("time_s,current_a,voltage_v,temperature_c\n" + rows + "\n")
    argv = ["replay", str(rec), "--no-send", "--record", str(tmp_path / "out.asc"), "--quiet",
            "--truth-out", str(tmp_path / "truth.csv")]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "truth.csv: the truth starts at" in err and "read from the OCV at 10 s, 1 s into a rest" in err
    assert main([*argv, "--soc0", "0.8"]) == 0
    assert "the truth starts at" not in capsys.readouterr().err


def test_the_bundled_drive_replays_from_the_full_charge_it_starts_at(tmp_path, capsys):
    """`socd replay pan18650pf_25C_US06` read the truth's start from a voltage a second into the drive's
    first rest (97.8 %) and warned it might be a few % off, where `socd demo` replays the same drive
    from the full charge it is known to start at (service/data/README.md)."""
    truth = tmp_path / "truth.csv"
    assert socd_main(["replay", "pan18650pf_25C_US06", "--no-send", "--cells", "2", "--stop", "60",
                      "--record", str(tmp_path / "d.asc"), "--truth-out", str(truth)]) == 0
    assert "relaxing" not in capsys.readouterr().err
    with truth.open() as fh:
        first = next(csv.DictReader(fh))
    assert float(first["soc_0"]) == 1.0 and float(first["soc_ref"]) == 1.0
    # a --soc0 given still wins
    assert socd_main(["replay", "pan18650pf_25C_US06", "--no-send", "--cells", "2", "--stop", "60", "--soc0", "0.9",
                      "--record", str(tmp_path / "e.asc"), "--truth-out", str(truth)]) == 0
    with truth.open() as fh:
        assert float(next(csv.DictReader(fh))["soc_0"]) == 0.9
