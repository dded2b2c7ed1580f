"""The whole chain in one process, on nothing but loopback (``socd demo``).

- a real drive cycle (the bundled excerpt in ``service/data/``) expanded to an N-cell pack
  with a seeded per-cell spread of capacity, resistance and start SOC
  (:func:`replay.pack.pack_frames`), replayed onto a python-can ``virtual`` bus whose
  channel is unique to this run (:func:`replay.player.play`, in a thread);
- the :class:`~service.daemon.daemon.Daemon` estimating from another Bus object on the same
  channel, publishing CAN output frames there and Zenoh on
  ``tcp/127.0.0.1:<free port>`` (multicast scouting off);
- a Zenoh subscriber session counting what arrives (callbacks bridged into the loop
  with ``loop.call_soon_threadsafe``), and a third Bus counting the CAN output frames;
- at the end, every cell's SOC error against the replay's truth, and its estimated capacity's
  error against the capacity the pack was built with.

:func:`run_demo` returns a :class:`DemoResult`; ``socd demo`` prints it and writes the
JSON and the plot.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import shutil
import socket
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import can
import numpy as np

from service.assets import bundled_recording

if TYPE_CHECKING:
    from replay.pack import StartSoc
    from service.recording import Recording

log = logging.getLogger(__name__)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class DemoResult:
    cells: int
    recording: str
    speed: float
    seconds_replayed: float
    wall_s: float
    frames_in: int
    frames_rejected: int
    values_rejected: int
    samples: int
    steps: int
    soc_rmse_pct: float
    soc_mae_pct: float
    soc_max_err_pct: float
    soc_rmse_after_600s_pct: float | None
    #: share of the samples after 600 s (all cells) whose error is within twice the σ the service
    #: published with them (95 % for an honest σ)
    soc_within_2sigma_pct: float | None
    per_cell_rmse_pct: list[float]
    #: per cell at the end: (estimated capacity / the cell's true capacity - 1), %
    capacity_err_pct: list[float]
    #: per cell at the end: the capacity's σ as the service publishes it, % of the estimate (0 when frozen)
    capacity_std_pct: list[float]
    capacity_spread: float
    #: per cell: (the cell's true capacity / the profile's - 1), %, as the seeded spread drew it
    true_capacity_pct: list[float]
    final_soc_pct: list[float]
    final_truth_pct: list[float]
    zenoh_messages: int
    zenoh_by_kind: dict[str, int]
    can_frames_out: int
    can_frames_seen: int
    frames_per_s: float
    #: CPU time of the whole demo process (daemon, replay thread, Zenoh subscriber) per wall time
    cpu_pct: float
    latency_ms: dict[str, float | None]
    status_flags: dict[str, bool]
    #: the recorded cell's true SOC at the first sample, %, and where it came from
    truth_start_soc_pct: float
    truth_start: str
    #: False where the start was read from a voltage still relaxing (the truth may be a few % off)
    truth_start_settled: bool
    counters: dict[str, int] = field(default_factory=dict)
    faults: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


SHIPPED_DBC_CELLS = 96
#: σ of the demo pack's relative cell capacity
DEFAULT_CAPACITY_SPREAD = 0.02


#: a demo whose pack empties (or fills) before this share of the drive is refused: the start SOC
#: leaves no room for the drive, and a few seconds of it show nothing
MIN_DEMO_SHARE = 0.1


def within_every_cell(recording: Recording, truth_soc: np.ndarray) -> tuple[Recording, int | None]:
    """``recording`` up to the first sample where a cell's true SOC leaves [0, 1], and that cell.

    A pack built from one recorded cell gives a cell with less capacity (or a lower start) than the
    recorded one a true SOC below 0 before the recording ends; a real pack's BMS stops the drive
    when its weakest cell is empty, and a SOC outside [0, 1] is no truth to score against."""
    from replay.pack import first_outside_unit

    if (first := first_outside_unit(truth_soc)) is None:
        return recording, None
    k, cell = first
    return recording.slice(0, max(2, k)), cell


def check_sample_step(recording: Recording) -> None:
    """Refuse a recording sampled more slowly than the service integrates (``MAX_STEP_S``): the
    daemon would reject every step and the demo would score nothing (a time column in ms, or an
    hourly log)."""
    from service.daemon.daemon import MAX_STEP_S
    from service.errors import UserError

    step = float(np.median(np.diff(recording.time_s))) if len(recording) > 1 else 0.0
    if step > MAX_STEP_S:
        raise UserError(f"{recording.path}: samples every {step:g} s (median); the service integrates steps of at "
                        f"most {MAX_STEP_S:g} s, so nothing would be estimated (is time_s in ms? socd evaluate "
                        "scores a slow log offline)")


def check_decodable(recording: Recording) -> None:
    """Refuse a recording whose voltages or temperatures lie outside the ranges the service
    accepts from the bus (the demo config's ``mapping.voltage_range_v``, ``temperature_range_c``):
    the daemon would count every such sample out of range and the demo would score nothing."""
    from service.config import MappingConfig
    from service.errors import UserError
    from service.validation import InputFileError, check_values

    mapping = MappingConfig()
    try:
        check_values(recording.path, {"voltage_v": recording.voltage_v, "temperature_c": recording.temperature_c},
                     {"voltage_v": mapping.voltage_range_v, "temperature_c": mapping.temperature_range_c})
    except InputFileError as exc:
        raise UserError(f"{exc} (the range the service reads from the bus: mapping.voltage_range_v, "
                        "mapping.temperature_range_c)") from None


def _generated_input_dbc(n_cells: int, workdir: Path) -> Path:
    """A BMS DBC for a pack larger than the shipped one, made by the generator of the shipped
    ones (same layout: 4 cells per voltage frame, one temperature sensor per 4 cells)."""
    from service.assets.dbc.generate_dbc import bms_database
    from service.config import MappingConfig

    cells_per_sensor = MappingConfig.model_fields["cells_per_sensor"].default  # the demo config's
    path = workdir / f"bms_pack_{n_cells}.dbc"
    path.write_text(bms_database(n_cells, -(-n_cells // cells_per_sensor)).as_dbc_string())
    return path


def _demo_config(n_cells: int, channel: str, port: int, workdir: Path, profile_path: Path):
    from service.config import DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC, build_config

    input_dbc = DEFAULT_INPUT_DBC
    if n_cells > SHIPPED_DBC_CELLS:
        input_dbc = _generated_input_dbc(n_cells, workdir)
    return build_config({
        "cell_profile": str(profile_path),
        "dbc": {"input": str(input_dbc), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": n_cells},
        "bus": {"interface": "virtual", "channel": channel},
        "output": {"can_period_s": 0.5, "zenoh_period_s": 0.25, "queue_size": 64},
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"], "connect": [],
                  "scouting_multicast": False, "key_prefix": "bms", "pack_id": "demo"},
        "checkpoint": {"path": str(workdir / "demo-state.ckpt"), "interval_s": 3600.0},
    })


def run_demo(
    cells: int = 8,
    speed: float = 0.0,
    seconds: float | None = None,
    *,
    recording_path: Path | None = None,
    start_soc: float | None = None,
    profile_path: Path | None = None,
    seed: int = 0,
    faults: Any = None,
    status: TextIO | bool | None = True,
    live: bool | None = None,
    capacity_spread: float = DEFAULT_CAPACITY_SPREAD,
    capacity_estimation: str | None = None,
) -> tuple[DemoResult, dict[str, np.ndarray]]:
    """Run the demo; return the result and the traces (``t_s``, ``soc``, ``truth``) for a plot.

    ``capacity_spread``: σ of the cells' relative capacity (clipped at ±3σ);
    ``capacity_estimation``: overrides ``estimator.capacity_estimation`` ("off" freezes it)."""
    from replay.pack import known_start
    from service.cell.profile import load_profile
    from service.cell.truth import check_current_sign
    from service.config import DEFAULT_CELL_PROFILE
    from service.recording import load_recording

    recording_path = Path(recording_path) if recording_path is not None else bundled_recording()
    start: float | StartSoc | None = start_soc if start_soc is not None else known_start(recording_path)
    profile_path = Path(profile_path) if profile_path else DEFAULT_CELL_PROFILE
    profile = load_profile(profile_path)
    recording = load_recording(recording_path)
    check_current_sign(recording)  # a charge-positive log would replay every cell the wrong way
    check_sample_step(recording)
    check_decodable(recording)
    if seconds is not None:
        stop_i = int(np.searchsorted(recording.time_s, recording.time_s[0] + float(seconds), side="right"))
        recording = recording.slice(0, max(2, stop_i))

    workdir = Path(tempfile.mkdtemp(prefix="socd-demo-"))
    try:  # the checkpoint and a generated DBC live there: removed however the demo ends
        return _demo_in(workdir, recording, recording_path, profile, profile_path, cells=cells, speed=speed,
                        start=start, seed=seed, faults=faults, status=status, live=live,
                        capacity_spread=capacity_spread, capacity_estimation=capacity_estimation)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def _demo_in(workdir: Path, recording: Recording, recording_path: Path, profile: Any, profile_path: Path, *,
             cells: int, speed: float, start: float | StartSoc | None, seed: int, faults: Any,
             status: TextIO | bool | None, live: bool | None, capacity_spread: float,
             capacity_estimation: str | None) -> tuple[DemoResult, dict[str, np.ndarray]]:
    """:func:`run_demo` from the pack's frames on: replay, estimate, publish, score (files in ``workdir``)."""
    import zenoh

    from replay.pack import SpreadSpec, pack_frames
    from replay.player import play
    from service.bus.encoder import decode_output
    from service.daemon.daemon import Daemon
    from service.daemon.zenoh_pub import zenoh_config
    from service.evaluation.metrics import within_2sigma_pct

    channel = f"socd-demo-{os.getpid()}-{time.monotonic_ns()}"
    port = free_port()
    config = _demo_config(cells, channel, port, workdir, profile_path)
    if capacity_estimation is not None:
        config = config.model_copy(update={"estimator": config.estimator.model_copy(
            update={"capacity_estimation": capacity_estimation})})
    spread = SpreadSpec(capacity=capacity_spread, resistance=0.05, soc=0.02, temperature_c=0.5)
    lazy_frames, pack = pack_frames(recording, config, profile, cells, spread, seed=seed, start_soc=start,
                                    lazy=True)
    full_span = float(recording.time_s[-1] - recording.time_s[0])
    recording, emptied = within_every_cell(recording, pack.truth_soc)
    kept = float(recording.time_s[-1] - recording.time_s[0])
    if emptied is not None and kept < MIN_DEMO_SHARE * full_span:
        from service.errors import UserError

        given = "the start SOC" + (f" {pack.start.soc:g}" if start is not None else "")
        raise UserError(f"cell {emptied}'s true SOC leaves [0, 1] {kept:.0f} s into the {full_span:.0f} s drive: "
                        f"{given} leaves the pack no room for it; give a --soc0 further from that end")
    if emptied is None:
        frames = list(lazy_frames)
    else:  # the same pack over the shorter recording (the spread is drawn from the seed alone)
        frames, pack = pack_frames(recording, config, profile, cells, spread, seed=seed, start_soc=start)
    if status is True:
        status = sys.stdout  # looked up now: the caller may have redirected it
    elif status is False:
        status = None
    if (caution := pack.start.caution()) is not None:
        log.warning("%s", caution)
    if emptied is not None and status is not None:
        print(f"replay stops at {recording.time_s[-1] - recording.time_s[0]:.0f} s, where cell {emptied} is "
              "empty (or full), as the pack's BMS would stop the drive", file=status)
    if live is None:
        live = status is not None and status.isatty()

    t_hist: list[float] = []
    soc_hist: list[np.ndarray] = []
    std_hist: list[np.ndarray] = []
    zenoh_counts: Counter[str] = Counter()
    can_seen: Counter[str] = Counter()
    replay_stats: list[Any] = []

    async def main() -> tuple[Daemon, float]:
        loop = asyncio.get_running_loop()
        daemon_bus = can.Bus(interface="virtual", channel=channel)
        tx_bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        out_bus = can.Bus(interface="virtual", channel=channel)
        out_db = config.output_db()

        def on_out(msg: can.Message) -> None:
            if msg.is_extended_id:
                name = decode_output(msg, out_db).get("message")
                if name:
                    can_seen[name] += 1

        out_notifier = can.Notifier(out_bus, [on_out], timeout=0.1)
        sub_session = None
        daemon = Daemon(config, daemon_bus, profile=profile, install_signal_handlers=False)
        daemon.step_listeners.append(lambda s: (t_hist.append(s.t_s), soc_hist.append(daemon.estimator.soc.copy()),
                                                std_hist.append(np.array(daemon.estimator.soc_std, dtype=float))))
        stop = asyncio.Event()
        run_task = asyncio.create_task(daemon.run(stop))
        stop_replay = threading.Event()
        try:
            await daemon.wait_started()
            # the dashboard side: Zenoh callbacks run on Zenoh's threads -> into the loop
            sub_session = zenoh.open(zenoh_config("peer", [], [f"tcp/127.0.0.1:{port}"], False))

            def count(key: str) -> None:
                kind = key.rsplit("/", 1)[-1]
                zenoh_counts[kind] += 1

            sub = sub_session.declare_subscriber(
                "bms/demo/**", lambda sample: loop.call_soon_threadsafe(count, str(sample.key_expr))
            )
            t0 = time.perf_counter()
            cpu0 = time.process_time()

            def replay() -> None:
                replay_stats.append(play(tx_bus, frames, speed=speed, faults=faults, stop_event=stop_replay,
                                         config=config))

            player = threading.Thread(target=replay, name="socd-demo-replay", daemon=True)
            player.start()
            last_line = 0.0
            while True:
                await asyncio.sleep(0.1)
                done = not player.is_alive()
                if done and replay_stats:
                    sent = replay_stats[0].frames_sent
                    if daemon.decoder.counters["frames_in"] >= sent and daemon.receiver.backlog() == 0:
                        break
                now = time.perf_counter()
                if status is not None and (now - last_line > (0.25 if live else 2.0)):
                    last_line = now
                    _status_line(status, daemon, now - t0, len(frames), sum(zenoh_counts.values()),
                                 sum(can_seen.values()), live)
            # one more publication round of each kind carries the final state
            await asyncio.sleep(max(config.output.zenoh_period_s, config.output.can_period_s) + 0.2)
            wall = time.perf_counter() - t0
            cpu = time.process_time() - cpu0
            if status is not None:
                _status_line(status, daemon, wall, len(frames), sum(zenoh_counts.values()),
                             sum(can_seen.values()), live)
                if live:
                    status.write("\n")
            sub.undeclare()
        finally:
            stop_replay.set()
            stop.set()
            await asyncio.wait_for(run_task, 30)
            out_notifier.stop()
            if sub_session is not None:
                sub_session.close()
            for b in (tx_bus, out_bus, daemon_bus):
                b.shutdown()
        return daemon, wall, cpu

    daemon, wall, cpu = asyncio.run(main())

    t = np.asarray(t_hist)
    soc = np.asarray(soc_hist).reshape(len(t_hist), cells) if t_hist else np.zeros((0, cells))
    std = np.asarray(std_hist).reshape(len(t_hist), cells) if t_hist else np.zeros((0, cells))
    idx = np.clip(np.searchsorted(pack.time_s, t), 0, len(pack.time_s) - 1)
    truth = pack.truth_soc[idx] if len(t) else np.zeros((0, cells))
    err = (soc - truth) * 100.0
    if err.size:
        rmse = float(np.sqrt(np.mean(err ** 2)))
        late = t - pack.time_s[0] >= 600.0
        rmse_late = float(np.sqrt(np.mean(err[late] ** 2))) if late.any() else None
        within = within_2sigma_pct(err[late], std[late]) if late.any() else None
        per_cell = np.sqrt(np.mean(err ** 2, axis=0))
    else:
        rmse, rmse_late, within, per_cell = float("nan"), None, None, np.full(cells, np.nan)
    counters = daemon.counters()
    health = daemon.estimator.health()
    capacity_err = (health.capacity_ah / pack.capacity_ah - 1.0) * 100.0
    capacity_std = health.capacity_std_ah / health.capacity_ah * 100.0
    result = DemoResult(
        cells=cells,
        recording=recording_path.name,
        speed=speed,
        seconds_replayed=float(recording.time_s[-1] - recording.time_s[0]),
        wall_s=round(wall, 3),
        frames_in=int(counters.get("frames_in", 0)),
        frames_rejected=int(counters.get("frames_rejected", 0)),
        values_rejected=int(counters.get("values_rejected", 0)),
        samples=daemon.samples,
        steps=daemon.steps,
        soc_rmse_pct=round(rmse, 4),
        soc_mae_pct=round(float(np.mean(np.abs(err))) if err.size else float("nan"), 4),
        soc_max_err_pct=round(float(np.max(np.abs(err))) if err.size else float("nan"), 4),
        soc_rmse_after_600s_pct=None if rmse_late is None else round(rmse_late, 4),
        soc_within_2sigma_pct=None if within is None else round(within, 2),
        per_cell_rmse_pct=[round(float(x), 4) for x in per_cell],
        capacity_err_pct=[round(float(x), 3) for x in capacity_err],
        capacity_std_pct=[round(float(x), 3) for x in capacity_std],
        capacity_spread=capacity_spread,
        true_capacity_pct=[round(100 * (float(x) / profile.effective_capacity_ah - 1.0), 3) for x in pack.capacity_ah],
        final_soc_pct=[round(100 * float(x), 3) for x in (soc[-1] if len(soc) else [])],
        final_truth_pct=[round(100 * float(x), 3) for x in (truth[-1] if len(truth) else [])],
        zenoh_messages=int(sum(zenoh_counts.values())),
        zenoh_by_kind=dict(zenoh_counts),
        can_frames_out=daemon.can_frames_out,
        can_frames_seen=int(sum(can_seen.values())),
        frames_per_s=round(counters.get("frames_in", 0) / wall, 1) if wall > 0 else 0.0,
        cpu_pct=round(100.0 * cpu / wall, 1) if wall > 0 else 0.0,
        latency_ms=daemon.health.latency_ms(),
        status_flags=daemon.status_flags(),
        counters=counters,
        faults=dict(replay_stats[0].faults) if replay_stats else {},
        truth_start_soc_pct=round(100 * pack.start.soc, 3),
        truth_start=pack.start.source,
        truth_start_settled=pack.start.settled,
    )
    traces = {"t_s": t - (pack.time_s[0] if len(pack.time_s) else 0.0), "soc": soc, "truth": truth, "std": std}
    return result, traces


def _status_line(out: TextIO, d: Any, wall: float, total: int, zmsgs: int, can_out: int, live: bool) -> None:
    c = d.decoder.counters
    soc = d.estimator.soc if d.initialised else None
    soc_txt = f"SOC {100 * float(np.mean(soc)):5.1f} % (min {100 * float(np.min(soc)):5.1f})" if soc is not None else "SOC   -  "
    line = (
        f"t={wall:5.1f}s frames {c['frames_in']:>7}/{total} rejected {d.decoder.rejected:>4} "
        f"steps {d.steps:>6} {soc_txt} zenoh msgs {zmsgs:>6} can out {can_out:>5}"
    )
    out.write(("\r" + line) if live else (line + "\n"))
    out.flush()


def write_plot(path: Path, traces: dict[str, np.ndarray], result: DemoResult) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, soc, truth = traces["t_s"], traces["soc"], traces["truth"]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    for i in range(soc.shape[1] if soc.ndim == 2 else 0):
        line, = ax1.plot(t, 100 * soc[:, i], lw=1.0)
        ax1.plot(t, 100 * truth[:, i], lw=0.8, ls="--", color=line.get_color())
        ax2.plot(t, 100 * (soc[:, i] - truth[:, i]), lw=0.8, color=line.get_color())
    ax1.set_ylabel("SOC, % (solid: estimate, dashed: truth)")
    ax1.set_title(f"socd demo: {result.cells} cells, {result.recording}; "
                  f"SOC RMSE {result.soc_rmse_pct:.2f} %")
    std = traces.get("std")
    if std is not None and len(t):  # the band the service publishes: ±2σ, the median over the cells
        band = 200 * np.median(std, axis=1)
        ax2.fill_between(t, -band, band, color="0.85", lw=0, label="±2σ published (median cell)")
        ax2.legend(loc="upper right", fontsize=8)
    ax2.set_ylabel("error, %")
    ax2.set_xlabel("recording time, s")
    ax2.axhline(0, color="k", lw=0.5)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_json(path: Path, result: DemoResult) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result.to_json(), indent=1, default=float) + "\n")
    return path


def summary_text(r: DemoResult) -> str:
    worst = int(np.argmax(r.per_cell_rmse_pct)) if r.per_cell_rmse_pct else 0
    lines = [
        (f"replayed {r.seconds_replayed:.0f} s of {r.recording} for {r.cells} cells in {r.wall_s:.1f} s "
         f"({r.frames_per_s:.0f} frames/s, CPU {r.cpu_pct:.0f} % of one core)"),
        (f"frames in {r.frames_in}, rejected {r.frames_rejected} (and {r.values_rejected} single values); "
         f"estimator steps {r.steps}"),
        f"SOC error vs truth: RMSE {r.soc_rmse_pct:.2f} %, MAE {r.soc_mae_pct:.2f} %, max {r.soc_max_err_pct:.2f} %"
        + (f", RMSE after 600 s {r.soc_rmse_after_600s_pct:.2f} %" if r.soc_rmse_after_600s_pct is not None else "")
        + (f", within its published 2σ {r.soc_within_2sigma_pct:.0f} % of the time after 600 s"
           if r.soc_within_2sigma_pct is not None else ""),
        (f"truth: the recorded cell starts at {r.truth_start_soc_pct:.1f} % SOC, {r.truth_start}"
         + ("" if r.truth_start_settled else " (still relaxing there: give --soc0 for a truth to trust)")),
        "per cell RMSE %: " + " ".join(f"{x:.2f}" for x in r.per_cell_rmse_pct)
        + (f"  (worst: cell {worst})" if r.per_cell_rmse_pct else ""),
        "per cell capacity error %: " + " ".join(f"{x:+.2f}" for x in r.capacity_err_pct)
        + f"  (capacity spread σ {100 * r.capacity_spread:g} %)",
        (f"Zenoh messages received {r.zenoh_messages} {dict(sorted(r.zenoh_by_kind.items()))}; "
         f"CAN output frames sent {r.can_frames_out}, seen {r.can_frames_seen}"),
        ("latency ms (frame -> estimate / -> Zenoh put): "
         f"p50 {r.latency_ms.get('estimate_p50')} / {r.latency_ms.get('publish_p50')}, "
         f"p99 {r.latency_ms.get('estimate_p99')} / {r.latency_ms.get('publish_p99')}"),
    ]
    raised = [k for k, v in r.status_flags.items() if v]
    lines.append("status flags: " + (", ".join(sorted(raised)) if raised else "none") + _flag_note(r, raised))
    return "\n".join(lines)


def _flag_note(r: DemoResult, raised: list[str]) -> str:
    """Why a flag a fast replay raises by design is up: the Zenoh publisher's queue drops its oldest
    round when full (service.daemon.zenoh_pub), and a drive replayed many times faster than real
    time fills it with rounds that newer ones carrying the same keys supersede."""
    pace = r.seconds_replayed / r.wall_s if r.wall_s > 0 else 0.0
    if "publish_drops" not in raised or pace < 2.0:
        return ""
    return (f" (the drive ran {pace:.0f}x faster than real time: the Zenoh publisher dropped queued rounds "
            "that newer ones superseded; --speed 1 replays in real time)")

