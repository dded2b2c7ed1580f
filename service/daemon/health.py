"""What the daemon counts, and the status word derived from it (DESIGN §6).

Every event that is not the happy path is counted by reason in :attr:`HealthMonitor.counters`
and, where it matters to a consumer, raises a status flag (names from
:data:`service.bus.types.STATUS_FLAGS`, plus ``checkpoint_corrupt`` in the Zenoh health
payload, which the CAN status word has no bit for).  Event flags are held for
:data:`FLAG_HOLD_S` after the last occurrence so a 10 Hz status frame cannot miss one.

Latency is measured from a frame's timestamp to (a) the end of the estimator step it
triggered and (b) the Zenoh ``put`` of a round that contains it.  Frame timestamps are wall
clock on SocketCAN and python-can's ``virtual`` bus; where a frame's timestamp is not
plausible wall time (a replayed log keeping its original times), its arrival time is used.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Mapping

import numpy as np

from service.bus.decoder import REJECT_REASONS, VALUE_REJECTS
from service.daemon.payloads import Health

#: seconds an event flag stays raised after the event
FLAG_HOLD_S = 10.0
#: samples kept for the latency percentiles
LATENCY_WINDOW = 4096
#: a frame timestamp further than this from the wall clock is not wall time
PLAUSIBLE_CLOCK_SKEW_S = 30.0

#: decoder frame outcomes that mean "frame rejected" (summed into ``frames_rejected``: every
#: frame is counted once, so ``frames_in = frames_decoded + frames_ignored + frames_rejected``)
DECODER_REJECT_REASONS: tuple[str, ...] = REJECT_REASONS

#: decoder reason -> event flag it raises
_DECODER_FLAGS: dict[str, str] = {
    "counter_jump": "counter_errors",
    "bad_dlc": "decode_errors",
    "decode_error": "decode_errors",
    "out_of_range": "decode_errors",
    "nan": "decode_errors",
    "timestamp_backwards": "decode_errors",
    "timestamp_jump": "decode_errors",
    "clock_reanchor": "clock_reanchored",
    "no_time_sync": "decode_errors",
    "time_sync_missing": "decode_errors",
}


def wall_time_of(frame_ts: float, arrival_wall: float) -> float:
    """The frame's timestamp if it is plausible wall-clock time, else its arrival time."""
    if abs(frame_ts - arrival_wall) <= PLAUSIBLE_CLOCK_SKEW_S:
        return frame_ts
    return arrival_wall


class HealthMonitor:
    """Counters by reason, event flags with hold time, latency percentiles.

    Thread-safe for :meth:`count` and :meth:`record_latency` (the Zenoh publisher thread
    calls them); everything else runs on the event loop.
    """

    def __init__(self, pack: str = "pack0", clock=time.monotonic) -> None:
        self.pack = pack
        self._clock = clock
        self._start = clock()
        self._lock = threading.Lock()
        self.counters: Counter[str] = Counter()
        self._event_at: dict[str, float] = {}
        self._latched: dict[str, bool] = {}
        self._latency: dict[str, deque[float]] = {
            "estimate": deque(maxlen=LATENCY_WINDOW),
            "publish": deque(maxlen=LATENCY_WINDOW),
        }
        self._decoder_seen: dict[str, int] = {}
        self.checkpoint_state = "not loaded"

    # -- recording ------------------------------------------------------------------------
    def count(self, reason: str, n: int = 1, flag: str | None = None) -> None:
        """Count ``n`` events of ``reason``; raise event flag ``flag`` for FLAG_HOLD_S."""
        if n <= 0:
            return
        with self._lock:
            self.counters[reason] += n
            if flag is not None:
                self._event_at[flag] = self._clock()

    def raise_flag(self, flag: str) -> None:
        """Raise an event flag without counting (the count lives elsewhere)."""
        with self._lock:
            self._event_at[flag] = self._clock()

    def set_flag(self, flag: str, value: bool) -> None:
        """A state flag: stays as set until set again."""
        with self._lock:
            self._latched[flag] = bool(value)

    def record_latency(self, kind: str, seconds: float) -> None:
        if seconds < 0 or not np.isfinite(seconds):
            return
        with self._lock:
            self._latency[kind].append(seconds * 1e3)

    def absorb_decoder(self, decoder_counters: Mapping[str, int]) -> None:
        """Raise flags for decoder reasons that grew since the last call."""
        for reason, flag in _DECODER_FLAGS.items():
            now = int(decoder_counters.get(reason, 0))
            if now > self._decoder_seen.get(reason, 0):
                self.raise_flag(flag)
            self._decoder_seen[reason] = now

    def reset_latency(self) -> None:
        """Forget the latency samples so far (a benchmark's warm-up)."""
        with self._lock:
            for d in self._latency.values():
                d.clear()

    # -- reading --------------------------------------------------------------------------
    def latency_values(self, kind: str) -> list[float]:
        """The latency samples of ``kind`` kept so far (ms, oldest first)."""
        with self._lock:
            return list(self._latency[kind])

    def latency_ms(self) -> dict[str, float | None]:
        out: dict[str, float | None] = {}
        with self._lock:
            data = {k: np.fromiter(v, dtype=float) for k, v in self._latency.items()}
        for kind, arr in data.items():
            if arr.size:
                p50, p99 = np.percentile(arr, [50, 99])
                out[f"{kind}_p50"], out[f"{kind}_p99"] = round(float(p50), 3), round(float(p99), 3)
            else:
                out[f"{kind}_p50"] = out[f"{kind}_p99"] = None
        return out

    def flags(self) -> dict[str, bool]:
        now = self._clock()
        with self._lock:
            out = dict(self._latched)
            for flag, at in self._event_at.items():
                out[flag] = out.get(flag, False) or (now - at) <= FLAG_HOLD_S
        return out

    def all_counters(self, decoder_counters: Mapping[str, int] | None = None) -> dict[str, int]:
        """Own counters merged with the decoder's, plus ``frames_rejected`` (whole frames) and
        ``values_rejected`` (single values of decoded frames: :data:`VALUE_REJECTS`)."""
        with self._lock:
            out = {k: int(v) for k, v in self.counters.items()}
        if decoder_counters is not None:
            for k, v in decoder_counters.items():
                out[k] = out.get(k, 0) + int(v)
            out["frames_rejected"] = sum(int(decoder_counters.get(r, 0)) for r in DECODER_REJECT_REASONS)
            out["values_rejected"] = sum(int(decoder_counters.get(r, 0)) for r in VALUE_REJECTS)
        return out

    def uptime_s(self) -> float:
        return self._clock() - self._start

    def payload(self, t_s: float, decoder_counters: Mapping[str, int] | None = None,
                flags: Mapping[str, bool] | None = None) -> Health:
        return Health(
            pack=self.pack,
            t_s=t_s,
            uptime_s=round(self.uptime_s(), 3),
            status_flags=dict(flags if flags is not None else self.flags()),
            counters=self.all_counters(decoder_counters),
            latency_ms=self.latency_ms(),
            checkpoint=self.checkpoint_state,
        )
