"""BMS frames in, :class:`PackSample` out: the one place the CAN bus meets the estimator.

``FrameDecoder.feed(msg)`` decodes one frame with cantools, keeps the latest value of every
mapped signal with its frame timestamp, and emits a :class:`PackSample` each time a valid
pack-current frame arrives (the current frame is the sample clock; DESIGN §3: time comes
from frame timestamps).  The sign/scale flip to "positive = discharge" happens here, once.

Bad input never raises (DESIGN §6).  Every rejection is counted by reason in
``self.counters``:

=====================  ==========================================================  ========
reason                 meaning                                                     frame
=====================  ==========================================================  ========
unknown_id             ID not in the input DBC                                      dropped
bad_dlc                payload length differs from the DBC message length          dropped
decode_error           cantools could not decode (e.g. unknown multiplexer value)  dropped
timestamp_backwards    older than the last accepted frame of the same ID           dropped
duplicate              same bytes (so same counter) as the previous frame of ID    dropped
counter_jump           rolling counter is not previous + 1 (mod 2^bits)            used
out_of_range           a mapped value outside the config's range (per value)       value
nan                    a mapped value NaN/inf (float signals; per value)            value
error_frame            CAN error frame                                              dropped
remote_frame           remote transmission request                                  dropped
=====================  ==========================================================  ========

plus ``frames_in``, ``frames_decoded``, ``frames_ignored`` (known ID, nothing mapped) and
``samples``.  A rejected value invalidates that cell/sensor at once (``fresh`` False) until a
valid value arrives; it is never replaced by an older or extrapolated value.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import can
import numpy as np

from service.bus.types import PackSample
from service.config import SocdConfig

#: reasons that drop a whole frame
FRAME_REJECTS = ("unknown_id", "bad_dlc", "decode_error", "timestamp_backwards", "duplicate",
                 "error_frame", "remote_frame")
#: reasons that drop one value
VALUE_REJECTS = ("out_of_range", "nan")
#: every reason counted as a rejection (``counter_jump`` is counted but the frame is used)
REJECT_REASONS = FRAME_REJECTS + VALUE_REJECTS

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
            self._by_id[(m.frame_id, bool(m.is_extended_frame))] = info

        self.counters: Counter[str] = Counter()
        self.voltage_v = np.full(self.n_cells, np.nan)
        self.voltage_t = np.full(self.n_cells, -np.inf)
        self.sensor_c = np.full(self.n_sensors, np.nan)
        self.sensor_t = np.full(self.n_sensors, -np.inf)
        self.current_a = math.nan
        self.last_current_t_s: float | None = None

    # -- public ------------------------------------------------------------------------
    def feed(self, msg: can.Message) -> list[PackSample]:
        """Decode one frame; return ``[PackSample]`` if it was a valid current frame, else ``[]``."""
        c = self.counters
        c["frames_in"] += 1
        try:
            return self._feed(msg)
        except Exception:  # noqa: BLE001 - never raise on bad input (DESIGN §6)
            c["decode_error"] += 1
            return []

    @property
    def rejected(self) -> int:
        """Frames and values rejected so far (all reasons in :data:`REJECT_REASONS`)."""
        return sum(self.counters[r] for r in REJECT_REASONS)

    def stats(self) -> dict[str, int]:
        """Counters as a plain dict with every reason present (for health output)."""
        out = {k: 0 for k in ("frames_in", "frames_decoded", "frames_ignored", "samples",
                              "counter_jump", *REJECT_REASONS)}
        out.update(self.counters)
        out["rejected"] = self.rejected
        return out

    def fresh_at(self, t_s: float) -> np.ndarray:
        """Which cells have valid, recent (``≤ stale_after_s`` old at ``t_s``) voltage and temperature."""
        stale = self.stale_after_s
        v_ok = np.isfinite(self.voltage_v) & (t_s - self.voltage_t <= stale)
        s_ok = np.isfinite(self.sensor_c) & (t_s - self.sensor_t <= stale)
        return v_ok & s_ok[self.sensor_of_cell]

    def sample_at(self, t_s: float) -> PackSample:
        """The latest values as a sample at ``t_s`` (current NaN if none valid yet)."""
        return PackSample(
            t_s=float(t_s),
            current_a=float(self.current_a),
            voltage_v=self.voltage_v.copy(),
            temperature_c=self.sensor_c[self.sensor_of_cell],
            fresh=self.fresh_at(t_s),
        )

    # -- internals ---------------------------------------------------------------------
    def _feed(self, msg: can.Message) -> list[PackSample]:
        c = self.counters
        if msg.is_error_frame:
            c["error_frame"] += 1
            return []
        if msg.is_remote_frame:
            c["remote_frame"] += 1
            return []
        info = self._by_id.get((msg.arbitration_id, bool(msg.is_extended_id)))
        if info is None:
            c["unknown_id"] += 1
            return []
        data = bytes(msg.data)
        if len(data) != info.length:
            c["bad_dlc"] += 1
            return []
        ts = float(msg.timestamp)
        if not math.isfinite(ts) or ts < info.last_ts:
            c["timestamp_backwards"] += 1
            return []
        if info.counter is not None and data == info.last_data:
            c["duplicate"] += 1
            return []
        if not info.targets and info.counter is None:
            info.last_ts = ts
            c["frames_ignored"] += 1
            return []
        try:
            values = info.message.decode(data, decode_choices=False, scaling=True)
        except Exception:  # noqa: BLE001 - cantools raises several kinds
            c["decode_error"] += 1
            return []
        c["frames_decoded"] += 1
        info.last_ts = ts
        info.last_data = data
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
            except (TypeError, ValueError):
                c["decode_error"] += 1
                v = math.nan
                ok = False
            else:
                if not math.isfinite(v):
                    c["nan"] += 1
                    ok = False
                else:
                    ok = True
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
        if not new_current:
            return []
        c["samples"] += 1
        return [self.sample_at(ts)]
