"""Checkpoints: atomic write, checksum, mismatch, and kill -9 of a real ``socd run``.

The kill -9 test runs ``socd run`` as a subprocess on python-can's ``remote`` interface
(python-can-remote, server bound to 127.0.0.1: works across processes without kernel CAN,
DESIGN §9), feeds it a real recording expanded to a small pack, kills it with SIGKILL and
checks that the restarted service resumes from the checkpoint (small σ, flag
``checkpoint_restored``) instead of starting from OCV (σ = 20 %, flag ``ocv_init``).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from service.cell.profile import load_profile
from service.config import DEFAULT_CELL_PROFILE, DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC, build_config
from service.daemon import checkpoint as ck
from service.daemon.checkpoint import (
    decode_checkpoint,
    load_checkpoint,
    profile_hash,
    save_checkpoint,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "panasonic_18650pf"
RECORDING = DATA / "pan18650pf_25C_US06.csv"


def _state(n: int = 4) -> dict:
    rng = np.random.default_rng(1)
    return {
        "ukf_x": rng.normal(size=(n, 4)),
        "ukf_P": np.tile(np.eye(4), (n, 1, 1)),
        "reset_count": np.arange(n),
        "flags": np.array([True, False, True, False][:n]),
        "nested": {"z": np.ones((n, 3))},
    }


def _save(path: Path, n: int = 4, phash: str = "abc") -> dict:
    st = _state(n)
    save_checkpoint(path, st, n_cells=n, profile_sha256=phash, t_s=123.4)
    return st


# -- unit: format, atomicity, checksum, mismatch ---------------------------------------------
def test_roundtrip_and_no_temp_files_left(tmp_path: Path) -> None:
    path = tmp_path / "state.ckpt"
    st = _save(path)
    res = load_checkpoint(path, n_cells=4, profile_sha256="abc")
    assert res.ok, res.detail
    assert res.meta["t_s"] == 123.4 and res.meta["n_cells"] == 4
    np.testing.assert_array_equal(res.state["ukf_x"], st["ukf_x"])
    np.testing.assert_array_equal(res.state["nested"]["z"], st["nested"]["z"])
    assert res.state["flags"].dtype == bool
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.ckpt"]


def test_crash_during_write_keeps_previous_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "state.ckpt"
    _save(path)
    before = path.read_bytes()

    def boom(*_a, **_k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ck.os, "replace", boom)
    with pytest.raises(OSError):
        save_checkpoint(path, _state(), n_cells=4, profile_sha256="abc", t_s=999.0)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.ckpt"]  # temp file cleaned up


def test_write_is_fsynced_then_renamed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(ck.os, "fsync", lambda fd: (calls.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(ck.os, "replace", lambda a, b: (calls.append("replace"), real_replace(a, b))[1])
    _save(tmp_path / "state.ckpt")
    assert calls == ["fsync", "replace", "fsync"]  # file, rename, directory


@pytest.mark.parametrize("where", ["payload", "meta", "truncate", "magic", "garbage", "empty"])
def test_corruption_is_detected(tmp_path: Path, where: str) -> None:
    path = tmp_path / "state.ckpt"
    _save(path)
    data = bytearray(path.read_bytes())
    if where == "payload":
        data[-40] ^= 0x01
    elif where == "meta":
        i = data.index(b"123.4")
        data[i:i + 5] = b"123.5"
    elif where == "truncate":
        data = data[: len(data) - 10]
    elif where == "magic":
        data[0:4] = b"XXXX"
    elif where == "garbage":
        data = bytearray(os.urandom(300))
    else:
        data = bytearray()
    path.write_bytes(bytes(data))
    res = load_checkpoint(path, n_cells=4, profile_sha256="abc")
    assert res.reason == "corrupt", res.detail
    assert res.state is None


def test_missing_and_mismatch(tmp_path: Path) -> None:
    path = tmp_path / "state.ckpt"
    assert load_checkpoint(path, n_cells=4, profile_sha256="abc").reason == "missing"
    _save(path)
    res = load_checkpoint(path, n_cells=5, profile_sha256="abc")
    assert res.reason == "mismatch" and "4 cells" in res.detail
    res = load_checkpoint(path, n_cells=4, profile_sha256="other")
    assert res.reason == "mismatch" and "profile" in res.detail


def test_profile_hash_changes_with_any_field() -> None:
    profile = load_profile(_profile_path())
    changed = profile.model_copy(update={"capacity_ah": profile.capacity_ah * 1.01})
    assert profile_hash(profile) == profile_hash(profile.model_copy())
    assert profile_hash(profile) != profile_hash(changed)


def test_decode_rejects_pickles(tmp_path: Path) -> None:
    # object arrays would need pickle; the writer refuses them so the reader never sees one
    with pytest.raises(ValueError):
        save_checkpoint(tmp_path / "x", {"a": np.array([object()])}, n_cells=1, profile_sha256="p")
    assert decode_checkpoint(b"").reason == "corrupt"


def test_decode_rejects_a_header_size_past_any_integer() -> None:
    from service.daemon.checkpoint import MAGIC

    res = decode_checkpoint(MAGIC + b'{"meta": {}, "sha256": "x", "payload_bytes": 1e400}\n')
    assert res.reason == "corrupt" and "bad header" in res.detail


# -- the daemon's reaction ---------------------------------------------------------------
def _profile_path() -> Path:
    return DEFAULT_CELL_PROFILE  # the bundled Panasonic NCR18650PF profile


def _config(tmp_path: Path, n_cells: int = 8, **extra):
    raw = {
        "cell_profile": str(_profile_path()),
        "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": n_cells},
        "bus": {"interface": "virtual", "channel": f"ck-{os.getpid()}-{time.monotonic_ns()}"},
        "output": {"zenoh_enabled": False, "can_period_s": 0.2},
        "zenoh": {"listen": ["tcp/127.0.0.1:0"], "scouting_multicast": False},
        "checkpoint": {"path": str(tmp_path / "state.ckpt"), "interval_s": 0.5},
    }
    for k, v in extra.items():
        raw.setdefault(k, {}).update(v) if isinstance(v, dict) else raw.__setitem__(k, v)
    return build_config(raw)


def _sample(n: int, t: float, v: float = 3.6):
    from service.bus.types import PackSample

    return PackSample(t_s=t, current_a=1.0, voltage_v=np.full(n, v), temperature_c=np.full(n, 25.0),
                      fresh=np.ones(n, dtype=bool))


@pytest.mark.parametrize("damage", ["corrupt", "mismatch_cells", "mismatch_profile", "text_state", "soc_outside",
                                    "negative_variance"])
def test_daemon_flags_unusable_checkpoint_and_starts_from_ocv(tmp_path: Path, damage: str) -> None:
    from service.daemon.daemon import Daemon

    config = _config(tmp_path)
    bus = can.Bus(interface="virtual", channel=config.bus.channel)
    try:
        d = Daemon(config, bus)
        d.on_sample(_sample(8, 0.0))
        d.on_sample(_sample(8, 0.1))
        assert d.save_checkpoint()
        path = Path(config.checkpoint.path)
        if damage == "corrupt":
            data = bytearray(path.read_bytes())
            data[-30] ^= 0xFF
            path.write_bytes(bytes(data))
        elif damage in ("text_state", "soc_outside", "negative_variance"):
            # checksummed, right shapes, but values this filter never writes
            state = d.estimator.get_state()
            if damage == "text_state":
                state["ukf_x"] = np.full(state["ukf_x"].shape, "a")
            elif damage == "soc_outside":
                state["ukf_x"][:, d.estimator.ukf.i_soc] = 7.0
            else:
                state["ukf_P"] = -np.abs(state["ukf_P"])
            save_checkpoint(path, state, n_cells=8, profile_sha256=d.profile_sha256)
        elif damage == "mismatch_cells":
            save_checkpoint(path, d.estimator.get_state(), n_cells=9, profile_sha256=d.profile_sha256)
        else:
            save_checkpoint(path, d.estimator.get_state(), n_cells=8, profile_sha256="another profile")

        d2 = Daemon(config, bus)
        outcome = d2.restore()
        assert outcome == ("corrupt" if damage == "corrupt" else "mismatch")
        flags = d2.status_flags()
        assert flags["ocv_init"] and not flags["checkpoint_restored"]
        assert flags["checkpoint_corrupt"] is (damage == "corrupt")
        health = d2.health.payload(0.0, d2.decoder.counters, flags)
        assert health.checkpoint.startswith(outcome)
        assert health.counters[f"checkpoint_{outcome}"] == 1
        # the bad file is kept for inspection, not silently overwritten
        assert not path.exists() and any(p.name.startswith("state.ckpt.") for p in tmp_path.iterdir())
        d2.on_sample(_sample(8, 5.0))
        assert d2.initialised and np.all(d2.estimator.soc_std > 0.1)  # OCV start, large σ
        snap = d2.snapshot()
        assert snap.status_flags["ocv_init"]
    finally:
        bus.shutdown()


def test_daemon_restores_valid_checkpoint(tmp_path: Path) -> None:
    from service.daemon.daemon import Daemon

    config = _config(tmp_path)
    bus = can.Bus(interface="virtual", channel=config.bus.channel)
    try:
        d = Daemon(config, bus)
        for k in range(60):  # long enough for the SOC filter to converge from its OCV start
            d.on_sample(_sample(8, 0.1 * k, 3.6 - 0.0005 * k))
        assert not d.status_flags()["ocv_init"]
        assert d.save_checkpoint()
        d2 = Daemon(config, bus)
        assert d2.restore() == "restored"
        np.testing.assert_allclose(d2.estimator.soc, d.estimator.soc)
        np.testing.assert_allclose(d2.estimator.soc_std, d.estimator.soc_std)
        flags = d2.status_flags()
        assert flags["checkpoint_restored"] and not flags["ocv_init"] and not flags["checkpoint_corrupt"]
    finally:
        bus.shutdown()


# -- kill -9 of a real ``socd run`` ---------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, proc: subprocess.Popen, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError("can_remote server exited")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"port {port} never opened")


class _Log:
    """Collects a subprocess's stderr lines on a thread; wait for a line without sleeping blind."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._t = threading.Thread(target=self._pump, args=(proc,), daemon=True)
        self._t.start()

    def _pump(self, proc: subprocess.Popen) -> None:
        for line in proc.stderr:  # type: ignore[union-attr]
            with self._cond:
                self.lines.append(line)
                self._cond.notify_all()

    def wait_for(self, text: str, timeout: float) -> str:
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                for line in self.lines:
                    if text in line:
                        return line
                left = end - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{text!r} not logged; log:\n" + "".join(self.lines[-30:]))
                self._cond.wait(left)


watchers: list = []


class _OutputWatcher:
    """Latest decoded SOCD_CellSoc and SOCD_Status frames seen on the bus."""

    def __init__(self, bus: can.BusABC) -> None:
        from service.bus.encoder import decode_output

        self.soc: dict[int, tuple[float, float]] = {}
        self.flags: dict[str, bool] = {}
        self.status_frames = 0

        def on_msg(msg: can.Message) -> None:
            d = decode_output(msg)
            if d.get("message") == "SOCD_CellSoc":
                self.soc[int(d["SOCD_SocCellIndex"])] = (d["SOCD_Soc"], d["SOCD_SocStd"])
            elif d.get("message") == "SOCD_Status":
                self.flags = d["flags"]
                self.status_frames += 1

        self.notifier = can.Notifier(bus, [on_msg], timeout=0.1)
        watchers.append(self)

    def clear(self) -> None:
        self.soc, self.flags, self.status_frames = {}, {}, 0

    def wait_status(self, timeout: float, n: int = 2) -> None:
        end = time.monotonic() + timeout
        while self.status_frames < n:
            if time.monotonic() > end:
                raise TimeoutError("no status frames from the daemon")
            time.sleep(0.05)


def test_kill9_then_restart_resumes_from_checkpoint(tmp_path: Path) -> None:
    if not RECORDING.is_file():
        pytest.skip(f"{RECORDING} not present")
    from replay.pack import SpreadSpec, pack_frames
    from replay.player import play
    from service.recording import load_recording

    n_cells = 8
    port = _free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "can_remote", "-i", "virtual", "-c", f"ck9-{port}",
         "-H", "127.0.0.1", "-p", str(port), "-v"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    procs: list[subprocess.Popen] = []
    buses: list[can.BusABC] = []
    stop_replay = threading.Event()
    try:
        _wait_port(port, server)
        url = f"ws://127.0.0.1:{port}/"
        ckpt = tmp_path / "state.ckpt"
        profile = load_profile(_profile_path())
        cfg_path = tmp_path / "socd.toml"
        cfg_path.write_text(
            f'cell_profile = "{_profile_path()}"\n'
            f'[bus]\ninterface = "remote"\nchannel = "{url}"\nreconnect_initial_s = 0.2\nreconnect_max_s = 1.0\n'
            f'[dbc]\ninput = "{DEFAULT_INPUT_DBC}"\noutput = "{DEFAULT_OUTPUT_DBC}"\n'
            f"[pack]\nn_cells = {n_cells}\n"
            f"[output]\nzenoh_enabled = false\ncan_period_s = 0.2\n"
            f'[zenoh]\nlisten = ["tcp/127.0.0.1:{_free_port()}"]\nscouting_multicast = false\n'
            f'[checkpoint]\npath = "{ckpt}"\ninterval_s = 0.5\n'
        )
        config = build_config({"cell_profile": str(_profile_path()), "pack": {"n_cells": n_cells},
                               "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)}})
        recording = load_recording(RECORDING)
        frames, _pack = pack_frames(recording, config, profile, n_cells, SpreadSpec(soc=0.02), seed=3)

        # replay client: keeps the recording's timestamps through the server's virtual bus
        tx = can.Bus(interface="remote", channel=url, preserve_timestamps=True)
        buses.append(tx)
        rx = can.Bus(interface="remote", channel=url)
        buses.append(rx)
        watcher = _OutputWatcher(rx)

        def start_socd() -> tuple[subprocess.Popen, _Log]:
            p = subprocess.Popen([sys.executable, "-m", "service.cli", "run", "--config", str(cfg_path)],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                 env={**os.environ, "PYTHONUNBUFFERED": "1"})
            procs.append(p)
            return p, _Log(p)

        proc, log = start_socd()
        log.wait_for("socd running", 30)
        assert "no checkpoint" in log.wait_for("no usable checkpoint", 1)  # logged at info

        # 10x real time (the 1 Hz recording: a sample every 100 ms of wall time)
        played: list = []

        def replay(part: list) -> None:
            played.append(play(tx, part, speed=10.0, stop_event=stop_replay))

        player = threading.Thread(target=replay, args=(frames,), daemon=True)
        player.start()
        # let it converge and write a few checkpoints
        end = time.monotonic() + 30
        while time.monotonic() < end:
            res = load_checkpoint(ckpt, n_cells=n_cells, profile_sha256=profile_hash(profile))
            if res.ok and res.meta["t_s"] is not None and res.meta["t_s"] - frames[0].timestamp > 60:
                break
            time.sleep(0.1)
        else:
            raise TimeoutError("no checkpoint written:\n" + "".join(log.lines[-20:]))
        watcher.wait_status(10)
        assert watcher.flags["ocv_init"] is not None
        stop_replay.set()  # the pack goes quiet, so what the restart publishes is the restored state
        player.join(10)
        time.sleep(0.7)  # > checkpoint.interval_s: the last checkpoint holds the last sample

        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        assert proc.returncode == -signal.SIGKILL
        saved = load_checkpoint(ckpt, n_cells=n_cells, profile_sha256=profile_hash(profile))
        assert saved.ok, saved.detail
        i_soc = saved.state["ukf_x"].shape[1] - 2  # states [U_branches..., SOC, U_h]
        saved_soc = saved.state["ukf_x"][:, i_soc]
        saved_std = np.sqrt(saved.state["ukf_P"][:, i_soc, i_soc])
        assert np.all(saved_std < 0.05), "estimator had not converged before the kill"

        watcher.clear()
        proc, log = start_socd()
        log.wait_for("socd running", 30)
        assert "restored" in log.wait_for("restored estimator state", 1)
        watcher.wait_status(10, n=2)
        assert watcher.flags["checkpoint_restored"] and not watcher.flags["ocv_init"]
        soc_pct = np.array([watcher.soc[i][0] for i in range(n_cells)])
        soc_std_pct = np.array([watcher.soc[i][1] for i in range(n_cells)])
        # exactly the checkpointed estimate (to the wire's 0.01 % resolution), not an OCV start
        np.testing.assert_allclose(soc_pct, np.clip(100 * saved_soc, 0, 100), atol=0.011)
        # the σ published: the filter's own and the considered errors' part, both checkpointed
        published_std = np.minimum(np.sqrt(saved_std**2 + saved.state["consider_entries"][0]), 0.5)
        np.testing.assert_allclose(soc_std_pct, 100 * published_std, atol=0.011)

        # the pack speaks again: estimation continues from there with a small σ
        stop_replay.clear()
        rest = frames[played[0].frames_in:]
        player = threading.Thread(target=replay, args=(rest,), daemon=True)
        player.start()
        watcher.clear()
        time.sleep(2.0)
        watcher.wait_status(10, n=2)
        assert not watcher.flags["ocv_init"] and not watcher.flags["stale_cells"]
        soc_pct = np.array([watcher.soc[i][0] for i in range(n_cells)])
        soc_std_pct = np.array([watcher.soc[i][1] for i in range(n_cells)])
        assert np.all(soc_std_pct < 5.0)  # an OCV start would say 20 %
        assert np.max(np.abs(soc_pct - np.clip(100 * saved_soc, 0, 100))) < 3.0
        stop_replay.set()
        player.join(10)
        proc.send_signal(signal.SIGTERM)
        proc.wait(15)
        assert proc.returncode == 0, "".join(log.lines[-20:])
        # it says how the run ended (it said nothing): what it estimated, where the state went
        assert f"state saved to {ckpt}" in log.wait_for("socd run: stopped after", 5)
    finally:
        stop_replay.set()
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(5)
        for w in watchers:
            w.notifier.stop()
        watchers.clear()
        for b in buses:
            try:
                b.shutdown()
            except Exception:  # noqa: BLE001
                pass
        server.terminate()
        server.wait(5)
