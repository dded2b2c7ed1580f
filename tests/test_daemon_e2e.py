"""End to end: replay of a real recording → CAN → Daemon → CAN output frames + Zenoh.

A real Panasonic 18650PF drive cycle is expanded to a small pack (seeded spread) and
replayed unpaced onto a python-can ``virtual`` bus whose Bus objects preserve the
recording's timestamps; the daemon estimates from another Bus object on the channel; the
test decodes the daemon's CAN output frames from a third one and subscribes to its Zenoh
keys on tcp/127.0.0.1 (multicast scouting off).

Every fault kind of the replay tool, a listener that raises, a receive error, a bus-off
error frame and a CAN server that dies and comes back are survived and counted.
"""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import can
import numpy as np
import pytest
import zenoh

from replay.faults import FaultSpec
from replay.pack import SpreadSpec, pack_frames
from replay.player import play
from service.bus.encoder import decode_output
from service.cell.profile import load_profile
from service.config import DEFAULT_CELL_PROFILE, DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC, build_config
from service.daemon.can_rx import CAN_ERR_BUSOFF, CanReceiver, GuardedNotifier
from service.daemon.daemon import Daemon
from service.daemon.health import HealthMonitor
from service.daemon.payloads import CellSoc, Health
from service.daemon.zenoh_pub import zenoh_config
from service.recording import load_recording

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
RECORDING = DATA / "panasonic_18650pf" / "pan18650pf_25C_US06.csv"
N_CELLS = 8

pytestmark = pytest.mark.skipif(not RECORDING.is_file(), reason=f"{RECORDING} not present")


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _profile_path() -> Path:
    return DEFAULT_CELL_PROFILE  # the bundled Panasonic NCR18650PF profile


def _config(tmp_path: Path, **bus):
    return build_config({
        "cell_profile": str(_profile_path()),
        "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": N_CELLS},
        "bus": {"interface": "virtual", "channel": f"e2e-{os.getpid()}-{time.monotonic_ns()}",
                "reconnect_initial_s": 0.05, "reconnect_max_s": 0.5, **bus},
        "output": {"can_period_s": 0.2, "zenoh_period_s": 0.1},
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{_port()}"], "connect": [],
                  "scouting_multicast": False, "key_prefix": "bms", "pack_id": "e2e"},
        "checkpoint": {"path": str(tmp_path / "state.ckpt"), "interval_s": 0.5},
    })


@pytest.fixture(scope="module")
def drive():
    """(frames, pack truth) for the first 1500 s of a real US06 run, 8 cells with spread."""
    profile = load_profile(_profile_path())
    rec = load_recording(RECORDING)
    stop = int(np.searchsorted(rec.time_s, rec.time_s[0] + 1500.0))
    rec = rec.slice(0, stop)
    config = build_config({"cell_profile": str(_profile_path()), "pack": {"n_cells": N_CELLS},
                           "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)}})
    spread = SpreadSpec(capacity=0.02, resistance=0.05, soc=0.02, temperature_c=0.5)
    frames, pack = pack_frames(rec, config, profile, N_CELLS, spread, seed=7)
    return frames, pack, profile


class _Chain:
    """Replay → daemon → (CAN output bus, Zenoh subscriber), run to completion."""

    def __init__(self, config, profile) -> None:
        self.config = config
        self.profile = profile
        self.can_out: Counter[str] = Counter()
        self.last_soc_frame: dict[int, dict] = {}
        self.last_status: dict = {}
        self.zenoh: Counter[str] = Counter()
        self.zenoh_soc: dict[int, CellSoc] = {}
        self.zenoh_health: Health | None = None
        self.t_hist: list[float] = []
        self.soc_hist: list[np.ndarray] = []
        self.replay = None

    async def run(self, frames, faults: FaultSpec | None = None, during=None, bus: can.BusABC | None = None) -> Daemon:
        cfg = self.config
        loop = asyncio.get_running_loop()
        channel = cfg.bus.channel
        own_bus = bus is None
        daemon_bus = can.Bus(interface="virtual", channel=channel) if own_bus else bus
        tx = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        out = can.Bus(interface="virtual", channel=channel)
        out_db = cfg.output_db()

        def on_out(msg: can.Message) -> None:
            d = decode_output(msg, out_db)
            name = d.get("message")
            if name:
                self.can_out[name] += 1
            if name == "SOCD_CellSoc":
                self.last_soc_frame[int(d["SOCD_SocCellIndex"])] = d
            elif name == "SOCD_Status":
                self.last_status = d

        out_notifier = can.Notifier(out, [on_out], timeout=0.1)
        d = Daemon(cfg, daemon_bus, profile=self.profile, install_signal_handlers=False)
        d.step_listeners.append(lambda s: (self.t_hist.append(s.t_s), self.soc_hist.append(d.estimator.soc.copy())))
        sess = zenoh.open(zenoh_config("peer", [], cfg.zenoh.listen, False))

        def on_zenoh(key: str, payload: str) -> None:  # on the loop
            kind = key.rsplit("/", 1)[-1]
            self.zenoh[kind] += 1
            if kind == "soc":
                c = CellSoc.model_validate_json(payload)
                self.zenoh_soc[c.cell] = c
            elif kind == "health":
                self.zenoh_health = Health.model_validate_json(payload)

        sub = sess.declare_subscriber(
            "bms/e2e/**",
            lambda s: loop.call_soon_threadsafe(on_zenoh, str(s.key_expr), s.payload.to_string()),
        )
        stop = asyncio.Event()
        task = asyncio.create_task(d.run(stop))
        try:
            await d.wait_started()
            result: list = []
            th = threading.Thread(target=lambda: result.append(play(tx, frames, faults=faults, config=cfg)))
            th.start()
            if during is not None:
                await during(d)
            end = time.monotonic() + 45
            while th.is_alive() or d.decoder.counters["frames_in"] < result[0].frames_sent or d.receiver.backlog():
                assert time.monotonic() < end, "daemon did not keep up"
                assert not task.done(), f"daemon stopped: {task.exception() if task.done() else ''}"
                await asyncio.sleep(0.05)
            self.replay = result[0]
            await asyncio.sleep(0.5)  # final CAN and Zenoh rounds
            assert not task.done(), "daemon stopped"
        finally:
            stop.set()
            await asyncio.wait_for(task, 20)
            sub.undeclare()
            sess.close()
            out_notifier.stop()
            tx.shutdown()
            out.shutdown()
            if own_bus:
                daemon_bus.shutdown()
        return d

    def errors_pct(self, pack) -> np.ndarray:
        t = np.asarray(self.t_hist)
        soc = np.asarray(self.soc_hist)
        idx = np.clip(np.searchsorted(pack.time_s, t), 0, len(pack.time_s) - 1)
        return 100.0 * (soc - pack.truth_soc[idx])


def test_replay_to_can_and_zenoh_outputs_with_bounded_soc_error(tmp_path: Path, drive) -> None:
    frames, pack, profile = drive
    chain = _Chain(_config(tmp_path), profile)
    d = asyncio.run(chain.run(frames))

    counters = d.counters()
    assert counters["frames_in"] == len(frames) and counters["frames_rejected"] == 0
    assert d.steps >= len(pack) - 2
    # CAN output: every cell's SOC frame, params, summary, status; values match the estimator
    assert set(chain.last_soc_frame) == set(range(N_CELLS))
    assert chain.can_out["SOCD_CellParams"] >= N_CELLS and chain.can_out["SOCD_PackSummary"] >= 1
    wire = np.array([chain.last_soc_frame[i]["SOCD_Soc"] for i in range(N_CELLS)])
    np.testing.assert_allclose(wire, np.clip(100 * d.estimator.soc, 0, 100), atol=0.02)
    assert chain.last_status["flags"]["ocv_init"] is False  # converged from the OCV start
    # Zenoh: every cell, same numbers, health with the decoder's counters
    assert set(chain.zenoh_soc) == set(range(N_CELLS))
    np.testing.assert_allclose([chain.zenoh_soc[i].soc_pct for i in range(N_CELLS)], 100 * d.estimator.soc, atol=1e-3)
    assert chain.zenoh["params"] >= N_CELLS and chain.zenoh["summary"] >= 1
    assert chain.zenoh_health is not None and chain.zenoh_health.counters["frames_in"] > 0
    # accuracy on the real recording (OCV start, then the drive cycle)
    err = chain.errors_pct(pack)
    late = np.asarray(chain.t_hist) - pack.time_s[0] > 300.0
    rmse_late = float(np.sqrt(np.mean(err[late] ** 2)))
    print(f"e2e SOC RMSE after 300 s {rmse_late:.2f} %, max {np.max(np.abs(err[late])):.2f} %")
    assert rmse_late < 4.5, f"SOC RMSE after 300 s {rmse_late:.2f} %"
    assert np.max(np.abs(err[late])) < 12.0
    lat = d.health.latency_ms()
    assert lat["estimate_p50"] is not None and lat["publish_p50"] is not None
    assert Path(d.config.checkpoint.path).is_file()  # final checkpoint on shutdown


FAULTS = {
    "drop": (FaultSpec(drop=0.05, seed=1), ["counter_jump"]),
    "duplicate": (FaultSpec(duplicate=0.05, seed=2), ["duplicate"]),
    # frames of one sample share its timestamp: a swap shows as a rolling-counter jump
    "reorder": (FaultSpec(reorder=0.05, seed=3), ["counter_jump|timestamp_backwards"]),
    "jitter": (FaultSpec(jitter_s=0.4, seed=4), []),
    "corrupt": (FaultSpec(corrupt=0.05, seed=5), ["bad_dlc"]),
    "stuck": (FaultSpec(stuck_cells=[(2, 100.0)], seed=6), []),
    "bus_gap": (FaultSpec(bus_gaps=[(200.0, 40.0)], seed=7), ["dt_gap_reinit|dt_gap_at_rest"]),
}


@pytest.mark.parametrize("kind", list(FAULTS))
def test_fault_injection_survived_and_counted(tmp_path: Path, drive, kind: str) -> None:
    frames, pack, profile = drive
    frames = [f for f in frames if f.timestamp - frames[0].timestamp < 400.0]
    spec, reasons = FAULTS[kind]
    chain = _Chain(_config(tmp_path), profile)
    d = asyncio.run(chain.run(frames, faults=spec))

    injected = chain.replay.faults
    assert sum(injected.values()) > 0, f"the replay injected nothing: {injected}"
    counters = d.counters()
    for reason in reasons:
        assert any(counters.get(r, 0) > 0 for r in reason.split("|")), (reason, counters)
    assert counters.get("internal_errors", 0) == 0
    # the estimate stays a number in range and keeps moving with the data
    assert d.steps > 0.8 * counters["samples"] - 5
    assert np.all(np.isfinite(d.estimator.soc)) and np.all((d.estimator.soc > -0.05) & (d.estimator.soc < 1.05))
    health = chain.zenoh_health
    assert health is not None and health.counters["frames_in"] > 0
    if kind != "stuck":
        good = np.arange(N_CELLS) != 2
        err = chain.errors_pct(pack)[:, good]
        late = np.asarray(chain.t_hist) - pack.time_s[0] > 300.0
        assert np.sqrt(np.mean(err[late] ** 2)) < 10.0


# -- the receive path: errors are never lost --------------------------------------------
class _FlakyBus(can.BusABC):
    """A virtual bus whose recv raises once after ``fail_after`` messages (a bus error)."""

    def __init__(self, channel: str, fail_after: int) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        self.fail_after = fail_after
        self.n = 0
        self.channel_info = f"flaky {channel}"
        super().__init__(channel=channel)

    def _recv_internal(self, timeout):
        msg = self._inner.recv(timeout)
        if msg is not None:
            self.n += 1
            if self.n == self.fail_after:
                raise can.CanOperationError("bus-off (injected)")
        return msg, False

    def send(self, msg, timeout=None):
        self._inner.send(msg, timeout)

    def shutdown(self):
        self._inner.shutdown()
        super().shutdown()


def _frames(n: int) -> list[can.Message]:
    return [can.Message(arbitration_id=0x123, data=[i % 256] * 8, is_extended_id=False) for i in range(n)]


def test_listener_exception_is_counted_and_delivery_continues() -> None:
    channel = f"lst-{time.monotonic_ns()}"

    async def main() -> tuple[list, list]:
        loop = asyncio.get_running_loop()
        rx = can.Bus(interface="virtual", channel=channel)
        tx = can.Bus(interface="virtual", channel=channel)
        seen: list[int] = []
        errors: list[BaseException] = []

        def listener(msg: can.Message) -> None:
            seen.append(msg.data[0])
            if msg.data[0] == 3:
                raise RuntimeError("listener bug")

        notifier = GuardedNotifier(rx, [listener], loop=loop, on_receive_error=errors.append,
                                   on_listener_error=errors.append)
        for m in _frames(10):
            tx.send(m)
        end = time.monotonic() + 5
        while len(seen) < 10 and time.monotonic() < end:
            await asyncio.sleep(0.01)
        notifier.stop()
        rx.shutdown()
        tx.shutdown()
        return seen, errors

    seen, errors = asyncio.run(main())
    assert seen == list(range(10))
    assert len(errors) == 1 and isinstance(errors[0], RuntimeError)


def test_receive_error_reconnects_with_backoff() -> None:
    channel = f"flaky-{time.monotonic_ns()}"

    async def main() -> tuple[list[int], HealthMonitor, float]:
        health = HealthMonitor()
        opened: list[float] = []
        buses: list[can.BusABC] = []

        def open_bus() -> can.BusABC:
            opened.append(time.monotonic())
            b = _FlakyBus(channel, fail_after=5 if len(opened) == 1 else 10**9)
            buses.append(b)
            return b

        rx = CanReceiver(health, open_bus=open_bus, reconnect_initial_s=0.2, reconnect_max_s=1.0)
        await rx.start()
        tx = can.Bus(interface="virtual", channel=channel)
        got: list[int] = []

        async def sender() -> None:
            for m in _frames(40):
                tx.send(m)
                await asyncio.sleep(0.02)

        st = asyncio.create_task(sender())
        end = time.monotonic() + 10
        while len(got) < 20 and time.monotonic() < end:
            try:
                msg = await asyncio.wait_for(rx.recv(), 0.5)
            except TimeoutError:
                continue
            got.append(msg.data[0])
        await st
        rx.close()
        tx.shutdown()
        gap = opened[1] - opened[0] if len(opened) > 1 else 0.0
        assert all(b._inner is not None for b in buses)
        return got, health, gap

    got, health, gap = asyncio.run(main())
    assert health.counters["bus_errors"] == 1 and health.counters["bus_reconnects"] == 1
    assert health.flags()["bus_error"]
    assert gap >= 0.2  # waited the initial backoff before reopening
    assert len(got) >= 20 and got == sorted(got)  # frames keep flowing after the reconnect


def test_bus_off_error_frame_triggers_reconnect() -> None:
    channel = f"busoff-{time.monotonic_ns()}"

    async def main() -> tuple[HealthMonitor, int]:
        health = HealthMonitor()
        bus = can.Bus(interface="virtual", channel=channel)
        rx = CanReceiver(health, bus=bus, reconnect_initial_s=0.05, reconnect_max_s=0.1)
        await rx.start()
        tx = can.Bus(interface="virtual", channel=channel)
        tx.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, data=[0] * 8))
        tx.send(can.Message(arbitration_id=0x10, data=[1], is_extended_id=False))
        err = await asyncio.wait_for(rx.recv(), 5)  # handed on, so the decoder counts it
        assert err.is_error_frame
        msg = await asyncio.wait_for(rx.recv(), 5)
        rx.close()
        bus.shutdown()
        tx.shutdown()
        return health, msg.arbitration_id

    health, arb = asyncio.run(main())
    assert health.counters["bus_off"] == 1 and health.flags()["bus_error"]
    assert health.counters["bus_reconnects"] == 1 and arb == 0x10


def test_can_server_dies_and_returns_daemon_reconnects(tmp_path: Path, drive) -> None:
    """A real cross-process bus (python-can-remote on 127.0.0.1) goes away and comes back."""
    frames, pack, profile = drive
    port = _port()
    args = [sys.executable, "-m", "can_remote", "-i", "virtual", "-c", f"srv-{port}", "-H", "127.0.0.1",
            "-p", str(port), "-v"]

    def start_server() -> subprocess.Popen:
        p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        end = time.monotonic() + 20
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                return p
            except OSError:
                assert p.poll() is None and time.monotonic() < end, "can_remote did not start"
                time.sleep(0.05)

    url = f"ws://127.0.0.1:{port}/"
    config = _config(tmp_path, interface="remote", channel=url)
    server = start_server()
    part1 = [f for f in frames if f.timestamp - frames[0].timestamp < 60.0]
    part2 = [f for f in frames if 80.0 <= f.timestamp - frames[0].timestamp < 140.0]

    async def main() -> tuple[Daemon, int, int]:
        nonlocal server
        d = Daemon(config, profile=profile, install_signal_handlers=False)
        stop = asyncio.Event()
        task = asyncio.create_task(d.run(stop))
        await d.wait_started()
        await asyncio.wait_for(d.receiver.connected.wait(), 10)

        def send(part) -> None:
            tx = can.Bus(interface="remote", channel=url, preserve_timestamps=True)
            try:
                play(tx, part, speed=0.0)
                time.sleep(0.2)
            finally:
                tx.shutdown()

        await asyncio.to_thread(send, part1)
        end = time.monotonic() + 20
        while d.decoder.counters["frames_in"] < len(part1):
            assert time.monotonic() < end
            await asyncio.sleep(0.05)
        steps1 = d.steps
        server.kill()
        server.wait(5)
        end = time.monotonic() + 10
        while d.health.counters["bus_errors"] == 0:
            assert time.monotonic() < end, "the dead server went unnoticed"
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.5)  # a few failed reopen attempts with backoff
        server = start_server()
        end = time.monotonic() + 15
        while not d.receiver.connected.is_set():
            assert time.monotonic() < end, "never reconnected"
            await asyncio.sleep(0.05)
        await asyncio.to_thread(send, part2)
        end = time.monotonic() + 20
        while d.decoder.counters["frames_in"] < len(part1) + len(part2):
            assert time.monotonic() < end, "frames after the reconnect did not arrive"
            await asyncio.sleep(0.05)
        assert not task.done()
        stop.set()
        await asyncio.wait_for(task, 20)
        return d, steps1, d.steps

    try:
        d, steps1, steps2 = asyncio.run(main())
    finally:
        server.kill()
        server.wait(5)
    c = d.health.counters
    assert c["bus_errors"] >= 1 and c["bus_reconnects"] >= 1
    assert steps2 > steps1 + 40  # estimation resumed on the new connection
    assert d.status_flags()["bus_error"]
