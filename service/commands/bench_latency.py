"""``socd bench --latency``: frame-to-Zenoh latency of the running service, on one core.

The whole service runs in this process, pinned to one CPU with everything around it: the
:class:`~service.daemon.daemon.Daemon` (default output settings: CAN output every
``can_period_s``, the full Zenoh round every ``zenoh_period_s``, SOC published when
estimated, ``min_publish_interval_s`` per key) reads a python-can ``virtual`` bus; a sender
thread puts a simulated drive of ``cells`` cells on it at ``rate_hz`` samples a second in
real time (each sample's voltage and temperature frames, then the pack-current frame that
completes it; python-can stamps each frame with the wall time it was sent); a Zenoh
subscriber session connects over ``tcp/127.0.0.1`` (multicast scouting off) to the
daemon's peer.

Two figures per sample, after a warm-up:

- **put**: the daemon's own measure (``publish`` latency of the health payload): the
  current frame's timestamp to the ``put`` of the summary of the estimate that frame
  completed (every cell's SOC key is put before it);
- **delivered**: the same frame timestamp (the payload's ``t_s``) to the subscriber's
  callback, for the summary and for the last cell's SOC key (the first arrival of each
  estimate: the full round repeats them later);

and, for the breakdown, **estimate**: the frame timestamp to the end of the estimator step.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from service.commands.bench_drive import pack_drive


@dataclass
class LatencyResult:
    cells: int
    rate_hz: float
    seconds: float
    warmup_s: float
    samples_sent: int
    samples_measured: int
    steps: int
    min_publish_interval_s: float
    estimate_ms: dict[str, float | None]
    put_ms: dict[str, float | None]
    delivered_summary_ms: dict[str, float | None]
    delivered_last_cell_ms: dict[str, float | None]
    cpu_pct: float
    step_ms_mean: float
    frames_rejected: int
    zenoh_dropped: int

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def percentiles(values_ms: list[float]) -> dict[str, float | None]:
    """p50 / p99 / max (ms, 3 decimals) and the count; None for an empty list."""
    if not values_ms:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    a = np.asarray(values_ms, dtype=float)
    p50, p99 = np.percentile(a, [50, 99])
    return {"p50": round(float(p50), 3), "p99": round(float(p99), 3), "max": round(float(a.max()), 3), "n": int(a.size)}


def _config(n_cells: int, channel: str, port: int, workdir: Path, profile_path: Path):
    from service.config import DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC, build_config
    from service.demo import SHIPPED_DBC_CELLS, _generated_input_dbc

    input_dbc = DEFAULT_INPUT_DBC if n_cells <= SHIPPED_DBC_CELLS else _generated_input_dbc(n_cells, workdir)
    return build_config({
        "cell_profile": str(profile_path),
        "dbc": {"input": str(input_dbc), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": n_cells},
        "bus": {"interface": "virtual", "channel": channel},
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"], "connect": [],
                  "scouting_multicast": False, "key_prefix": "bms", "pack_id": "bench"},
        "checkpoint": {"path": str(workdir / "bench-state.ckpt"), "interval_s": 60.0},
    })


def run_latency(cells: int = 200, rate_hz: float = 10.0, seconds: float = 60.0, warmup_s: float = 5.0,
                profile_path: Path | None = None) -> LatencyResult:
    """Run the service for ``warmup_s + seconds`` of real time and measure (see the module doc)."""
    from service.cell.profile import load_profile
    from service.config import DEFAULT_CELL_PROFILE

    profile_path = Path(profile_path) if profile_path else DEFAULT_CELL_PROFILE
    profile = load_profile(profile_path)
    workdir = Path(tempfile.mkdtemp(prefix="socd-bench-latency-"))
    try:  # the checkpoint and a generated DBC live there: removed however the run ends
        return _latency_in(workdir, profile, profile_path, cells, rate_hz, seconds, warmup_s)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def _latency_in(workdir: Path, profile: Any, profile_path: Path, cells: int, rate_hz: float, seconds: float,
                warmup_s: float) -> LatencyResult:
    """:func:`run_latency` from the config on (its files in ``workdir``)."""
    import zenoh

    from replay.pack import FrameBuilder
    from service.daemon.daemon import Daemon
    from service.daemon.zenoh_pub import zenoh_config
    from service.demo import free_port

    channel = f"socd-bench-{os.getpid()}-{time.monotonic_ns()}"
    port = free_port()
    config = _config(cells, channel, port, workdir, profile_path)
    dt = 1.0 / rate_hz
    total = int(round((warmup_s + seconds) * rate_hz))
    current, volts = pack_drive(profile, cells, total, dt, hold=max(1, int(round(1.0 / dt))))
    n_sensors = len(config.mapping.temperature_signals)
    builder = FrameBuilder(config)
    # frames built before the clock starts: the sender only sends (their timestamps are
    # replaced by the bus with the wall time of sending)
    per_sample = [builder.frames_for_sample(0.0, float(current[k]), volts[k], np.full(n_sensors, 25.0))
                  for k in range(total)]
    #: first arrival per estimate (frame time): a full round repeats the summary later
    summary_ms: dict[float, float] = {}
    cell_ms: dict[float, float] = {}
    measure_from = [float("inf")]  # wall time after the warm-up
    last_key = f"bms/bench/cell/{cells - 1}/soc"

    def on_sample(sample: Any) -> None:  # a Zenoh thread
        now = time.time()
        key = str(sample.key_expr)
        t_s = json.loads(sample.payload.to_bytes())["t_s"]
        if t_s >= measure_from[0]:
            (summary_ms if key.endswith("/summary") else cell_ms).setdefault(t_s, 1e3 * (now - t_s))

    async def main() -> tuple[Daemon, int, float, float]:
        daemon_bus = can.Bus(interface="virtual", channel=channel)
        tx_bus = can.Bus(interface="virtual", channel=channel)
        daemon = Daemon(config, daemon_bus, profile=profile, install_signal_handlers=False)
        stop = asyncio.Event()
        run_task = asyncio.create_task(daemon.run(stop))
        sub_session = None
        stop_tx = threading.Event()
        sent = [0]

        def sender() -> None:
            wall0 = time.perf_counter()
            for k, frames in enumerate(per_sample):
                due = wall0 + k * dt
                delay = due - time.perf_counter()
                if delay > 0 and stop_tx.wait(delay):
                    return
                for f in frames:
                    tx_bus.send(f)
                sent[0] += 1

        try:
            await daemon.wait_started()
            sub_session = zenoh.open(zenoh_config("peer", [], [f"tcp/127.0.0.1:{port}"], False))
            subs = [sub_session.declare_subscriber("bms/bench/summary", on_sample),
                    sub_session.declare_subscriber(last_key, on_sample)]
            tx = threading.Thread(target=sender, name="socd-bench-sender", daemon=True)
            wall_start = time.time()
            measure_from[0] = wall_start + warmup_s
            tx.start()
            await asyncio.sleep(warmup_s)
            daemon.health.reset_latency()
            steps0, cpu0, w0 = daemon.steps, time.process_time(), time.perf_counter()
            while tx.is_alive():
                await asyncio.sleep(0.1)
            await asyncio.sleep(0.5)  # the last sample's puts
            cpu_pct = 100.0 * (time.process_time() - cpu0) / (time.perf_counter() - w0)
            for s in subs:
                s.undeclare()
            return daemon, daemon.steps - steps0, cpu_pct, sent[0]
        finally:
            stop_tx.set()
            stop.set()
            await asyncio.wait_for(run_task, 30)
            if sub_session is not None:
                sub_session.close()
            tx_bus.shutdown()
            daemon_bus.shutdown()

    daemon, steps, cpu_pct, sent = asyncio.run(main())
    lat = daemon.health.latency_values("publish")
    counters = daemon.counters()
    return LatencyResult(
        cells=cells, rate_hz=rate_hz, seconds=seconds, warmup_s=warmup_s, samples_sent=sent,
        samples_measured=len(lat), steps=steps,
        min_publish_interval_s=config.output.min_publish_interval_s,
        estimate_ms=percentiles(daemon.health.latency_values("estimate")),
        put_ms=percentiles(lat), delivered_summary_ms=percentiles(list(summary_ms.values())),
        delivered_last_cell_ms=percentiles(list(cell_ms.values())), cpu_pct=round(cpu_pct, 1),
        step_ms_mean=round(1e3 * daemon.step_time_s / max(1, daemon.steps), 3),
        frames_rejected=int(counters.get("frames_rejected", 0)), zenoh_dropped=int(counters.get("zenoh_dropped", 0)),
    )


def result_text(r: LatencyResult) -> str:
    def row(name: str, p: dict[str, float | None]) -> str:
        if p["n"] == 0:
            return f"  {name:34s} (none)"
        return f"  {name:34s} p50 {p['p50']:7.2f} ms   p99 {p['p99']:7.2f} ms   max {p['max']:7.2f} ms   n {p['n']}"

    return "\n".join([
        f"frame -> Zenoh, {r.cells} cells x {r.rate_hz:g} Hz for {r.seconds:g} s (after {r.warmup_s:g} s warm-up), "
        f"one core, tcp/127.0.0.1, min_publish_interval_s {r.min_publish_interval_s:g}",
        row("estimate (end of the estimator step)", r.estimate_ms),
        row("put (summary, all cells before it)", r.put_ms),
        row("delivered: summary", r.delivered_summary_ms),
        row(f"delivered: cell {r.cells - 1} SOC", r.delivered_last_cell_ms),
        f"  CPU {r.cpu_pct:.0f} % of the core, estimator step {r.step_ms_mean:.2f} ms, "
        f"{r.samples_sent} samples sent, frames rejected {r.frames_rejected}, zenoh dropped {r.zenoh_dropped}",
    ])
