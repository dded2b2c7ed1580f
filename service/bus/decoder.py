"""BMS frames in, :class:`PackSample` out: the one place the CAN bus meets the estimator.

``FrameDecoder.feed(msg)`` decodes one frame with cantools, keeps the latest value of every
mapped signal with its frame timestamp, and emits a :class:`PackSample` each time a valid
pack-current frame arrives (the current frame is the sample clock; DESIGN §3: time comes
from frame timestamps).  The sign/scale flip to "positive = discharge" happens here, once.

Bad input never raises (DESIGN §6).  Every frame fed is counted exactly once, in
``frames_in`` and in one outcome, so ``frames_in == frames_decoded + frames_ignored +
rejected`` always holds:

=====================  ==========================================================
outcome                meaning
=====================  ==========================================================
frames_decoded         decoded and used (values may still be rejected one by one)
frames_ignored         ID in the input DBC, but nothing in it is mapped
unknown_id             ID not in the input DBC                                    (reject)
bad_dlc                payload length differs from the DBC message length         (reject)
decode_error           cantools could not decode (e.g. unknown multiplexer value) (reject)
timestamp_backwards    up to ``max_clock_jump_s`` older than the ID's last frame  (reject)
timestamp_jump         further than ``max_clock_jump_s`` from the ID's timeline,  (reject)
                       or not a finite number
no_time_sync           time sync on, and no time-sync frame accepted yet          (reject)
duplicate              same bytes (so same counter) as the previous frame of ID   (reject)
error_frame            CAN error frame                                            (reject)
remote_frame           remote transmission request                                (reject)
=====================  ==========================================================

Events inside decoded frames are counted on their own and are not frame outcomes:
``counter_jump`` (rolling counter is not previous + 1; the frame is used),
``out_of_range`` and ``nan`` (per *value*: that cell/sensor is invalidated, the rest of the
frame is used), ``clock_reanchor``, ``timestamp_rollback``, ``time_sync_missing`` (see below)
and ``samples``.  A rejected value
invalidates that cell/sensor at once (``fresh`` False) until a valid value arrives; it is
never replaced by an older or extrapolated value.

Time: a frame whose timestamp is off its ID's timeline (backwards, or more than
``mapping.max_clock_jump_s`` ahead; before an ID's first frame, the last accepted frame of
any ID is the timeline) is rejected without moving the reference, so one bad timestamp
costs only its own frame.  When the bad timestamp was accepted because it was only a little
ahead (within the bound), the ID's next good frame is older than it but not older than the
last frame accepted from another ID: the ID then rolls back to it (``timestamp_rollback``,
the next sample carries ``reanchored=True``).  A genuine clock jump (or a bus silent for longer than
``max_clock_jump_s``) shows as :data:`REANCHOR_AFTER` off-timeline frames in a row, of any
IDs, within ``max_clock_jump_s`` of each other: the decoder then re-anchors every ID on the
new timeline, counts ``clock_reanchor``, and the next sample carries ``reanchored=True``.

Time sync: when ``mapping.time_signal`` names a signal (:mod:`service.bus.timesync`), the
sender's sample time on the bus replaces arrival time, so a replay faster than real time onto
a kernel bus, which stamps frames on arrival, keeps the recording's time steps.  The frame
carrying the time is then the only clock: its decoded (unwrapped) value goes through the
timeline checks above in place of its timestamp (rejected as ``timestamp_jump`` /
``timestamp_backwards``, ``timestamp_rollback`` when the next one is older than it but not
older than the one before it, ``clock_reanchor`` after :data:`REANCHOR_AFTER` agreeing ones in
a row; the same bytes again are a ``duplicate``), and every other frame takes the latest
accepted time, whatever its timestamp.  A frame before the first accepted time has no time and
is rejected as ``no_time_sync``.  A pack-current frame with no new accepted time since the
previous sample (its time frame was lost or rejected) completes no sample and counts
``time_sync_missing`` (an event, its frame is ``frames_decoded``): the sample's time is unknown.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import can
import numpy as np

from service.bus.timesync import TimeSignal
from service.bus.types import PackSample
from service.config import SocdConfig

#: reasons that reject a whole frame (each frame is counted under at most one)
FRAME_REJECTS = ("unknown_id", "bad_dlc", "decode_error", "timestamp_backwards", "timestamp_jump",
                 "duplicate", "error_frame", "remote_frame", "no_time_sync")
#: reasons that reject one value of a decoded frame (counted per value)
VALUE_REJECTS = ("out_of_range", "nan")
#: frame outcomes that are not rejections
FRAME_ACCEPTS = ("frames_decoded", "frames_ignored")
#: every frame outcome counted as a rejection (``rejected`` and ``frames_rejected`` sum these)
REJECT_REASONS = FRAME_REJECTS
#: consecutive agreeing off-timeline frames of one ID after which it re-anchors on them
REANCHOR_AFTER = 5


def message_key(message) -> tuple[int, bool]:
    """A DBC message's ``(frame id, extended)``: the key a frame is decoded by (:func:`frame_key`)."""
    return message.frame_id, bool(message.is_extended_frame)


def frame_key(msg: can.Message) -> tuple[int, bool]:
    """A frame's ``(arbitration id, extended)``, matched against :func:`message_key`."""
    return msg.arbitration_id, bool(msg.is_extended_id)


_CURRENT, _VOLT, _TEMP = 0, 1, 2


@dataclass
class _MsgInfo:
    message: object  # cantools Message
    length: int
    targets: dict[str, tuple[int, int]]  # signal name -> (kind, index)
    counter: str | None = None
    counter_mod: int = 16
    last_ts: float = -math.inf
    last_counter: int | None = None
    last_data: bytes | None = None
    has_current: bool = False
    extra: dict = field(default_factory=dict)


class FrameDecoder:
    """Stateful decoder of the BMS bus for one pack (not thread-safe; one task feeds it)."""

    def __init__(self, config: SocdConfig, db=None) -> None:
        self.config = config
        self.db = db if db is not None else config.input_db()
        mp = config.mapping
        self.n_cells = config.pack.n_cells
        self.stale_after_s = float(mp.stale_after_s)
        self.max_jump_s = float(mp.max_clock_jump_s)
        self.current_factor = float(mp.current_sign) * float(mp.current_scale)
        self.v_lo, self.v_hi = mp.voltage_range_v
        self.t_lo, self.t_hi = mp.temperature_range_c
        self.i_lo, self.i_hi = mp.current_range_a
        self.n_sensors = len(mp.temperature_signals)
        self.sensor_of_cell = np.array(mp.sensor_of_cell(self.n_cells), dtype=int)

        targets: dict[str, tuple[int, int]] = {mp.current_signal: (_CURRENT, 0)}
        for i, s in enumerate(mp.cell_voltage_signals):
            targets[s] = (_VOLT, i)
        for k, t in enumerate(mp.temperature_signals):
            targets[t.signal] = (_TEMP, k)

        self._by_id: dict[tuple[int, bool], _MsgInfo] = {}
        for m in self.db.messages:
            names = {s.name for s in m.signals}
            info = _MsgInfo(message=m, length=m.length,
                            targets={n: targets[n] for n in names if n in targets})
            info.has_current = mp.current_signal in names
            cname = mp.counter_signals.get(m.name)
            if cname is not None and cname in names:
                sig = m.get_signal_by_name(cname)
                info.counter = cname
                info.counter_mod = 1 << sig.length
            self._by_id[message_key(m)] = info

        #: the signal carrying the sample time, and its message (None: frame timestamps)
        self.time_signal: TimeSignal | None = None
        self._sync_info: _MsgInfo | None = None
        if mp.time_signal is not None:
            self.time_signal = TimeSignal.find(self.db, mp.time_signal)
            m = self.time_signal.message
            self._sync_info = self._by_id[message_key(m)]
        #: the latest accepted time-sync value, the one accepted before it, and whether a
        #: sample has been completed since the latest
        self.sync_t_s: float | None = None
        self._sync_prev_t_s: float | None = None
        self._sync_fresh = False

        self.counters: Counter[str] = Counter()
        self.voltage_v = np.full(self.n_cells, np.nan)
        self.voltage_t = np.full(self.n_cells, -np.inf)
        self.sensor_c = np.full(self.n_sensors, np.nan)
        self.sensor_t = np.full(self.n_sensors, -np.inf)
        self.current_a = math.nan
        self.last_current_t_s: float | None = None
        #: timestamp of the last accepted frame of any ID (the timeline for a new ID)
        self.timeline_t_s: float | None = None
        self._reanchor_pending = False
        self._last_key: _MsgInfo | None = None  # the ID of the last accepted frame
        #: off-timeline frames seen in a row (any ID) that agree with each other: a clock jump?
        self._cand_ts: float | None = None
        self._cand_n = 0

    # -- public ------------------------------------------------------------------------
    def feed(self, msg: can.Message) -> list[PackSample]:
        """Decode one frame; return ``[PackSample]`` if it was a valid current frame, else ``[]``."""
        c = self.counters
        c["frames_in"] += 1
        samples: list[PackSample] = []
        try:
            outcome = self._feed(msg, samples)
        except Exception:  # noqa: BLE001 - never raise on bad input (DESIGN §6)
            outcome, samples = "decode_error", []
        c[outcome] += 1
        if samples:
            c["samples"] += 1
        return samples

    @property
    def rejected(self) -> int:
        """Frames rejected so far (sum over :data:`REJECT_REASONS`)."""
        return sum(self.counters[r] for r in REJECT_REASONS)

    def stats(self) -> dict[str, int]:
        """Counters as a plain dict with every reason present (for health output)."""
        out = {k: 0 for k in ("frames_in", *FRAME_ACCEPTS, "samples", "counter_jump", "clock_reanchor", "timestamp_rollback",
                              "time_sync_missing", *REJECT_REASONS, *VALUE_REJECTS)}
        out.update(self.counters)
        out["rejected"] = self.rejected
        return out

    def fresh_at(self, t_s: float) -> np.ndarray:
        """Which cells have valid, recent (``≤ stale_after_s`` from ``t_s``) voltage and temperature."""
        stale = self.stale_after_s
        v_ok = np.isfinite(self.voltage_v) & (np.abs(t_s - self.voltage_t) <= stale)
        s_ok = np.isfinite(self.sensor_c) & (np.abs(t_s - self.sensor_t) <= stale)
        return v_ok & s_ok[self.sensor_of_cell]

    def sample_at(self, t_s: float, reanchored: bool = False) -> PackSample:
        """The latest values as a sample at ``t_s`` (current NaN if none valid yet)."""
        return PackSample(
            t_s=float(t_s),
            current_a=float(self.current_a),
            voltage_v=self.voltage_v.copy(),
            temperature_c=self.sensor_c[self.sensor_of_cell],
            fresh=self.fresh_at(t_s),
            reanchored=reanchored,
        )

    # -- internals ---------------------------------------------------------------------
    def _off_timeline(self, info: _MsgInfo, ts: float) -> str | None:
        """The reject reason if ``ts`` is off this ID's timeline, else None."""
        if not math.isfinite(ts):
            return "timestamp_jump"
        ref = info.last_ts if info.last_ts > -math.inf else self.timeline_t_s
        if ref is None:
            return None
        if ts < ref:
            return "timestamp_backwards" if ref - ts <= self.max_jump_s else "timestamp_jump"
        if ts - ref > self.max_jump_s:
            return "timestamp_jump"
        return None

    def _ahead_of_bus(self, info: _MsgInfo, ts: float) -> bool:
        """An ID's frame older than its own last one but not older than the last frame the
        bus accepted from another ID: that last one of this ID was the outlier.  With time
        sync the time frame is the only clock: the outlier is its last value when this one is
        not older than the value accepted before that."""
        if info is self._sync_info:
            return self._sync_prev_t_s is not None and ts >= self._sync_prev_t_s
        return (self._last_key is not None and self._last_key is not info
                and self.timeline_t_s is not None and ts >= self.timeline_t_s)

    def _clock_jumped(self, ts: float) -> bool:
        """Note an off-timeline frame; True once :data:`REANCHOR_AFTER` in a row agree."""
        if not math.isfinite(ts):
            self._cand_ts, self._cand_n = None, 0
            return False
        prev = self._cand_ts
        # frames of one sample may come slightly out of order across IDs: agree = close
        if prev is not None and abs(ts - prev) <= self.max_jump_s:
            self._cand_n += 1
        else:
            self._cand_n = 1
        self._cand_ts = ts
        return self._cand_n >= REANCHOR_AFTER

    def _reanchor(self, info: _MsgInfo) -> None:
        """Follow the new timeline: every ID's reference is forgotten, this frame sets it."""
        self.counters["clock_reanchor"] += 1
        for other in self._by_id.values():
            other.last_ts = -math.inf
        info.last_data = None
        info.last_counter = None
        self.sync_t_s = self._sync_prev_t_s = None  # the old timeline says nothing about the new one
        self._reanchor_pending = True

    def _accept_sync(self, ts: float) -> None:
        """``ts`` is the latest time; the one before it stays after a rollback (``ts`` older)."""
        if self.sync_t_s is not None and ts > self.sync_t_s:
            self._sync_prev_t_s = self.sync_t_s
        self.sync_t_s = ts
        self._sync_fresh = True

    def _on_timeline(self, info: _MsgInfo, ts: float) -> str | None:
        """None if a frame of ``info`` at ``ts`` is accepted (after a rollback or a
        re-anchor if need be), else the reason it is rejected."""
        off = self._off_timeline(info, ts)
        if off == "timestamp_backwards" and self._ahead_of_bus(info, ts):
            # this ID's previous frame was stamped ahead of the bus, not this one behind it
            self.counters["timestamp_rollback"] += 1
            info.last_ts = -math.inf
            info.last_data = None
            info.last_counter = None
            self._reanchor_pending |= info.has_current or info is self._sync_info
            off = None
        if off is not None:
            if not self._clock_jumped(ts):
                return off
            self._reanchor(info)  # a run of agreeing frames: the clock really moved
        self._cand_ts, self._cand_n = None, 0
        return None

    def _sync_time(self, values: dict) -> float:
        """The time a decoded time-sync frame carries, unwrapped near the latest one (NaN if unreadable)."""
        assert self.time_signal is not None
        try:
            v = float(values[self.time_signal.name])
        except (KeyError, TypeError, ValueError, OverflowError):
            return math.nan
        return self.time_signal.unwrap(v, self.sync_t_s)

    def _feed(self, msg: can.Message, out: list[PackSample]) -> str:
        """Process one frame, append the sample it completes to ``out``; return its outcome."""
        c = self.counters
        if msg.is_error_frame:
            return "error_frame"
        if msg.is_remote_frame:
            return "remote_frame"
        info = self._by_id.get(frame_key(msg))
        if info is None:
            return "unknown_id"
        data = bytes(msg.data)
        if len(data) != info.length:
            return "bad_dlc"
        values: dict | None = None
        is_sync = info is self._sync_info
        if self._sync_info is None or is_sync:
            if is_sync:  # the time is in the payload: decode first
                try:
                    values = info.message.decode(data, decode_choices=False, scaling=True)
                except Exception:  # noqa: BLE001 - cantools raises several kinds
                    return "decode_error"
                ts = self._sync_time(values)
            else:
                ts = float(msg.timestamp)
            off = self._on_timeline(info, ts)
            if off is not None:
                return off
            # the time itself is the sync frame's counter: the same bytes again are a repeat
            if (info.counter is not None or is_sync) and data == info.last_data:
                return "duplicate"
        else:  # time sync: every other frame belongs to the latest accepted time
            if self.sync_t_s is None:
                return "no_time_sync"
            ts = self.sync_t_s
            if info.counter is not None and data == info.last_data:
                return "duplicate"
        on_clock = self._sync_info is None or is_sync  # the frames that set the timeline
        if not info.targets and info.counter is None and not is_sync:
            info.last_ts = ts
            if on_clock:
                self.timeline_t_s, self._last_key = ts, info
            return "frames_ignored"
        if values is None:
            try:
                values = info.message.decode(data, decode_choices=False, scaling=True)
            except Exception:  # noqa: BLE001 - cantools raises several kinds
                return "decode_error"
        info.last_ts = ts
        if on_clock:
            self.timeline_t_s, self._last_key = ts, info
        info.last_data = data
        if is_sync:
            self._accept_sync(ts)
        if info.counter is not None:
            cnt = values.get(info.counter)
            if cnt is not None:
                try:
                    cnt = int(cnt) % info.counter_mod
                except (TypeError, ValueError, OverflowError):
                    cnt = None
            if cnt is not None:
                if info.last_counter is not None and cnt != (info.last_counter + 1) % info.counter_mod:
                    c["counter_jump"] += 1
                info.last_counter = cnt

        new_current = False
        targets = info.targets
        for name, raw in values.items():
            tgt = targets.get(name)
            if tgt is None:
                continue
            kind, idx = tgt
            try:
                v = float(raw)
            except (TypeError, ValueError, OverflowError):
                v = math.nan
            ok = math.isfinite(v)
            if not ok:
                c["nan"] += 1
            if kind == _VOLT:
                if ok and not (self.v_lo <= v <= self.v_hi):
                    c["out_of_range"] += 1
                    ok = False
                self.voltage_v[idx] = v if ok else math.nan
                self.voltage_t[idx] = ts
            elif kind == _TEMP:
                if ok and not (self.t_lo <= v <= self.t_hi):
                    c["out_of_range"] += 1
                    ok = False
                self.sensor_c[idx] = v if ok else math.nan
                self.sensor_t[idx] = ts
            else:
                if ok:
                    v = v * self.current_factor
                    if not (self.i_lo <= v <= self.i_hi):
                        c["out_of_range"] += 1
                        ok = False
                if ok:
                    self.current_a = v
                    self.last_current_t_s = ts
                    new_current = True
                else:
                    self.current_a = math.nan
        if new_current:
            if self._sync_info is not None:
                if not self._sync_fresh:  # this sample's time frame was lost or rejected
                    c["time_sync_missing"] += 1
                    return "frames_decoded"
                self._sync_fresh = False
            out.append(self.sample_at(ts, self._reanchor_pending))
            self._reanchor_pending = False
        return "frames_decoded"
