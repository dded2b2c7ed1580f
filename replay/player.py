"""Put frames on a bus (and/or into a log), paced by their timestamps.

``play(bus, frames, speed=1.0)`` sends in real time; ``speed=2`` twice as fast; ``speed=0``
as fast as the bus takes them.  Frames keep their timestamps (a python-can ``virtual`` bus
opened with ``preserve_timestamps=True`` hands them to the receiver unchanged, so an
unpaced replay still gives the estimator the recording's time).  Log files of every
format python-can reads are streamed with :func:`read_log`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can

from replay.faults import FaultInjector, FaultSpec

#: suffixes python-can reads and writes (``.mf4`` needs the ``python-can[mf4]`` extra)
LOG_SUFFIXES = (".asc", ".blf", ".csv", ".log", ".mf4", ".trc")

_SEND_RETRIES = 5


@dataclass
class ReplayStats:
    frames_in: int = 0
    frames_sent: int = 0
    frames_failed: int = 0
    frames_skipped: int = 0  # outside --start/--stop
    loops: int = 0
    duration_s: float = 0.0  # wall clock
    span_s: float = 0.0  # recording time covered
    max_lag_s: float = 0.0  # worst lateness behind the pacing schedule
    stopped: bool = False
    faults: dict[str, int] = field(default_factory=dict)

    @property
    def frames_per_s(self) -> float:
        return self.frames_sent / self.duration_s if self.duration_s > 0 else math.inf


def log_format(path: str | Path) -> str | None:
    """The python-can log format of ``path`` (``".blf"``; ``".log"`` for ``x.log.gz``), or None."""
    suffixes = [s.lower() for s in Path(path).suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    return suffixes[-1] if suffixes and suffixes[-1] in LOG_SUFFIXES else None


def read_log(path: str | Path) -> Iterator[can.Message]:
    """Frames of a python-can log file (asc, blf, csv, log, mf4, trc, or any of them .gz), one at a time."""
    path = Path(path)
    fmt = log_format(path)
    if path.suffix.lower() == ".gz" and fmt is not None and len(path.suffixes) != 2:
        # python-can finds the format of a .gz only in "name.fmt.gz": open it the same way for "a.b.fmt.gz"
        import gzip

        from can.io.player import MESSAGE_READERS

        reader_type = MESSAGE_READERS[fmt]
        binary = fmt in (".blf", ".mf4")
        with reader_type(gzip.open(path, mode="rb" if binary else "rt")) as reader:
            yield from reader
        return
    with can.LogReader(path) as reader:
        yield from reader


class _Progress:
    """The replay's bar (rich, with ETA when the frame count is known) and its recording time."""

    def __init__(self, total: int | None, enabled: bool, stream=None) -> None:
        from service.commands.progress import open_progress

        self._bar = open_progress(enabled, "replay", total, unit="frames", stream=stream)
        self._last = 0.0

    def update(self, n: int, rel_s: float, force: bool = False) -> None:
        if not self._bar.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < 0.2:
            return
        self._last = now
        self._bar.update(completed=n, description=f"replay t={rel_s:9.2f} s")

    def close(self) -> None:
        self._bar.close()


def _window(frames: Iterable[can.Message], start: float | None, stop: float | None,
            stats: ReplayStats) -> Iterator[can.Message]:
    t0 = None
    for m in frames:
        if t0 is None:
            t0 = m.timestamp
        rel = m.timestamp - t0
        if start is not None and rel < start:
            stats.frames_skipped += 1
            continue
        if stop is not None and rel >= stop:
            stats.frames_skipped += 1
            break
        yield m


def _looped(frames: list[can.Message], loops: int | None, stats: ReplayStats) -> Iterator[can.Message]:
    """Repeat ``frames`` with timestamps shifted so time keeps increasing across loops."""
    if not frames:
        return
    first, last = frames[0].timestamp, frames[-1].timestamp
    period = 0.0
    if len(frames) > 1:
        gaps = [b.timestamp - a.timestamp for a, b in zip(frames, frames[1:]) if b.timestamp > a.timestamp]
        period = sorted(gaps)[len(gaps) // 2] if gaps else 0.0
    shift_per_loop = (last - first) + max(period, 1e-3)
    k = 0
    while loops is None or k < loops:
        shift = k * shift_per_loop
        for m in frames:
            if shift:
                m = can.Message(timestamp=m.timestamp + shift, arbitration_id=m.arbitration_id,
                                is_extended_id=m.is_extended_id, is_remote_frame=m.is_remote_frame,
                                is_error_frame=m.is_error_frame, dlc=m.dlc, data=m.data, is_fd=m.is_fd,
                                bitrate_switch=m.bitrate_switch, channel=m.channel)
            yield m
        k += 1
        stats.loops = k


def play(
    bus: can.BusABC | None,
    frames: Iterable[can.Message],
    speed: float = 0.0,
    faults: FaultSpec | FaultInjector | None = None,
    stop_event: threading.Event | None = None,
    progress: bool = False,
    *,
    start: float | None = None,
    stop: float | None = None,
    loop: bool | int = False,
    listeners: Iterable[Callable[[can.Message], object] | can.Listener] = (),
    total: int | None = None,
    config=None,
    send_timeout: float = 0.1,
) -> ReplayStats:
    """Send ``frames`` to ``bus`` (may be None: only ``listeners``, e.g. a ``can.Logger``).

    ``speed``: 1 = real time, 0 = unpaced.  ``start``/``stop`` select recording time (s from
    the first frame).  ``loop``: True = forever (until ``stop_event``), an int = that many
    passes.  ``faults`` are applied after the window and the looping.  Returns counts;
    never raises for a frame the bus refuses (counted in ``frames_failed``).
    """
    stats = ReplayStats()
    if speed < 0:
        raise ValueError("speed must be >= 0")
    stream: Iterable[can.Message] = _window(frames, start, stop, stats)
    if loop:
        stream = _looped(list(stream), None if loop is True else int(loop), stats)
        total = None
    injector: FaultInjector | None
    if isinstance(faults, FaultInjector):
        injector = faults
    elif faults is not None and faults.active:
        injector = FaultInjector(faults, config=config)
    else:
        injector = None
    if injector is not None:
        stream = injector.apply(stream)
    sinks = [ls.on_message_received if isinstance(ls, can.Listener) else ls for ls in listeners]
    bar = _Progress(total if total else (len(frames) if isinstance(frames, list) and not loop else None), progress)

    wall0 = time.perf_counter()
    rec0: float | None = None
    rel = 0.0
    try:
        for msg in stream:
            if stop_event is not None and stop_event.is_set():
                stats.stopped = True
                break
            stats.frames_in += 1
            if rec0 is None:
                rec0 = msg.timestamp
            rel = msg.timestamp - rec0
            if speed > 0:
                due = wall0 + rel / speed
                delay = due - time.perf_counter()
                if delay > 0.0005:
                    if stop_event is not None:
                        if stop_event.wait(delay):
                            stats.stopped = True
                            break
                    else:
                        time.sleep(delay)
                elif delay < 0:
                    stats.max_lag_s = max(stats.max_lag_s, -delay)
            for sink in sinks:
                sink(msg)
            if bus is not None:
                if _send(bus, msg, send_timeout):
                    stats.frames_sent += 1
                else:
                    stats.frames_failed += 1
            else:
                stats.frames_sent += 1
            bar.update(stats.frames_in, rel)
    finally:
        bar.update(stats.frames_in, rel, force=True)
        bar.close()
        stats.duration_s = time.perf_counter() - wall0
        stats.span_s = rel
        if injector is not None:
            stats.faults = dict(injector.counts)
    return stats


def _send(bus: can.BusABC, msg: can.Message, timeout: float) -> bool:
    delay = 0.001
    for _ in range(_SEND_RETRIES):
        try:
            bus.send(msg, timeout=timeout)
            return True
        except can.CanOperationError:
            # ENOBUFS on a flooded socket, a full virtual queue: back off briefly and retry
            time.sleep(delay)
            delay *= 4
        except can.CanError:
            return False
    return False
