"""The optional Prometheus /metrics endpoint, scraped with a real HTTP GET on 127.0.0.1."""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time
import urllib.request
from pathlib import Path

import can
import numpy as np
import pytest

pytest.importorskip("prometheus_client")
from prometheus_client.parser import text_string_to_metric_families

from replay.pack import SpreadSpec, pack_frames
from replay.player import play
from service.cell.profile import load_profile
from service.config import DEFAULT_CELL_PROFILE, DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC, build_config
from service.daemon.daemon import Daemon
from service.daemon.health import HealthMonitor
from service.daemon.metrics import MetricsError, MetricsServer
from service.recording import load_recording

RECORDING = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "panasonic_18650pf" / \
    "pan18650pf_25C_US06.csv"
N_CELLS = 4


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _scrape(port: int) -> dict[str, dict[tuple, float]]:
    """``{sample name: {labels: value}}`` from GET http://127.0.0.1:port/metrics."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
        assert resp.status == 200
        text = resp.read().decode()
    out: dict[str, dict[tuple, float]] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out.setdefault(s.name, {})[tuple(sorted(s.labels.items()))] = s.value
    return out


def test_metrics_server_exports_health_counters_and_latency() -> None:
    health = HealthMonitor(pack="t")
    health.count("frames_in", 5)
    health.count("bus_reconnects", 2, flag="bus_error")
    m = MetricsServer(health.all_counters, health.flags, health.uptime_s, 3, port=0)
    m.attach(health)
    port = m.start()
    try:
        assert m._server.server_address[0] == "127.0.0.1"  # loopback by default
        health.record_latency("estimate", 0.0015)
        health.record_latency("publish", 0.004)
        health.record_latency("publish", 0.3)
        got = _scrape(port)
        assert got["socd_events_total"][(("reason", "frames_in"),)] == 5
        assert got["socd_events_total"][(("reason", "bus_reconnects"),)] == 2
        assert got["socd_status_flag"][(("flag", "bus_error"),)] == 1
        assert got["socd_cells"][()] == 3
        count = got["socd_latency_seconds_count"]
        assert count[(("stage", "estimate"),)] == 1 and count[(("stage", "publish"),)] == 2
        buckets = got["socd_latency_seconds_bucket"]
        assert buckets[(("le", "0.005"), ("stage", "publish"))] == 1  # 4 ms in, 300 ms not
        assert buckets[(("le", "0.5"), ("stage", "publish"))] == 2
        # the monitor still has its own percentiles
        assert health.latency_ms()["estimate_p50"] == pytest.approx(1.5)
        # the port is taken now: a second server says so instead of raising OSError
        with pytest.raises(MetricsError, match=f"127.0.0.1:{port}"):
            MetricsServer(health.all_counters, health.flags, health.uptime_s, 3, port=port).start()
    finally:
        m.stop()
    with pytest.raises(OSError):
        urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=2)


@pytest.mark.skipif(not RECORDING.is_file(), reason=f"{RECORDING} not present")
def test_daemon_serves_metrics_while_estimating(tmp_path: Path) -> None:
    """A running daemon with [metrics] enabled: frames in, latency to estimate and to Zenoh publication."""
    profile = load_profile(DEFAULT_CELL_PROFILE)
    rec = load_recording(RECORDING)
    rec = rec.slice(0, int(np.searchsorted(rec.time_s, rec.time_s[0] + 200.0)))
    channel = f"metrics-{os.getpid()}-{time.monotonic_ns()}"
    config = build_config({
        "cell_profile": str(DEFAULT_CELL_PROFILE),
        "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": N_CELLS},
        "bus": {"interface": "virtual", "channel": channel},
        "output": {"can_enabled": False, "zenoh_period_s": 0.1},
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{_port()}"], "connect": [],
                  "scouting_multicast": False},
        "checkpoint": {"path": str(tmp_path / "state.npz")},
        "metrics": {"enabled": True, "port": 0},
    })
    frames, _ = pack_frames(rec, config, profile, N_CELLS, SpreadSpec(), seed=1)

    async def scenario() -> dict:
        daemon_bus = can.Bus(interface="virtual", channel=channel)
        tx = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        d = Daemon(config, daemon_bus, profile=profile, install_signal_handlers=False)
        stop = asyncio.Event()
        task = asyncio.create_task(d.run(stop))
        try:
            await d.wait_started()
            sender = threading.Thread(target=play, args=(tx, frames))
            sender.start()
            end = time.monotonic() + 30
            while sender.is_alive() or d.decoder.counters["frames_in"] < len(frames) or d.receiver.backlog():
                assert time.monotonic() < end and not task.done()
                await asyncio.sleep(0.05)
            while d.publisher.rounds_published < 2 and time.monotonic() < end:
                await asyncio.sleep(0.05)
            port = d.metrics.port
            return await asyncio.to_thread(_scrape, port)
        finally:
            stop.set()
            await asyncio.wait_for(task, 20)
            tx.shutdown()
            daemon_bus.shutdown()

    got = asyncio.run(scenario())
    assert got["socd_events_total"][(("reason", "frames_in"),)] == len(frames)
    assert got["socd_events_total"][(("reason", "steps"),)] >= len(rec) - 2
    assert got["socd_cells"][()] == N_CELLS
    count = got["socd_latency_seconds_count"]
    assert count[(("stage", "estimate"),)] >= len(rec) - 2
    assert count[(("stage", "publish"),)] >= 1
    assert (("flag", "zenoh_down"),) in got["socd_status_flag"]
