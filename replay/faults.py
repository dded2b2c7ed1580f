"""Seeded fault injection on a stream of CAN frames (DESIGN §6: every fault the daemon survives).

All times are seconds relative to the first frame's timestamp, so the same spec works for a
generated pack (recording time) and for a log file (epoch time).

============== ==========================================================================
fault          effect (what the decoder should count)
============== ==========================================================================
drop P         frame not sent (cells go stale after ``stale_after_s``)
duplicate P    frame sent twice (``duplicate``)
reorder P      frame held back and sent after the next one (``timestamp_backwards`` when
               both have the same ID; otherwise just late)
jitter S       timestamps delayed by U(0, S), kept in order (irregular sample intervals)
corrupt P      one payload bit flipped, or the DLC changed by ±1 byte (``bad_dlc``,
               ``decode_error``, ``out_of_range``, ``counter_jump`` or a silently wrong value)
stuck I[:T0]   cell I's voltage frozen at its value at T0 (needs the DBC and mapping)
bus gap T0:D   no frames in [T0, T0 + D) (everything goes stale)
============== ==========================================================================
"""

from __future__ import annotations

import copy
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Literal

import can
import numpy as np


@dataclass
class FaultSpec:
    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    jitter_s: float = 0.0
    corrupt: float = 0.0
    corrupt_mode: Literal["any", "bitflip", "dlc"] = "any"
    stuck_cells: list[tuple[int, float]] = field(default_factory=list)  # (cell, t0 relative)
    bus_gaps: list[tuple[float, float]] = field(default_factory=list)  # (t0 relative, duration)
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("drop", "duplicate", "reorder", "corrupt"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} probability must be in [0, 1], got {p}")
        if self.jitter_s < 0:
            raise ValueError(f"jitter must be >= 0 s, got {self.jitter_s}")
        for t0, d in self.bus_gaps:
            if d <= 0:
                raise ValueError(f"bus gap duration must be > 0, got {d}")

    @property
    def active(self) -> bool:
        return bool(self.drop or self.duplicate or self.reorder or self.jitter_s or self.corrupt
                    or self.stuck_cells or self.bus_gaps)


class FaultInjector:
    """Applies a :class:`FaultSpec` to frames; ``counts`` says what it did."""

    def __init__(self, spec: FaultSpec, config=None, db=None) -> None:
        self.spec = spec
        self.rng = np.random.default_rng(spec.seed)
        self.counts: Counter[str] = Counter()
        self._t0: float | None = None
        self._last_ts = -np.inf
        self._stuck: dict[str, tuple[float, object, float | None]] = {}  # signal -> (t0, msg, frozen value)
        self._stuck_msgs: dict[int, object] = {}
        if spec.stuck_cells:
            if config is None:
                raise ValueError("stuck cells need a config (DBC + mapping) to find the cell's signal")
            db = db if db is not None else config.input_db()
            for cell, t0 in spec.stuck_cells:
                if not 0 <= cell < len(config.mapping.cell_voltage_signals):
                    raise ValueError(f"stuck cell {cell} outside 0..{len(config.mapping.cell_voltage_signals) - 1}")
                name = config.mapping.cell_voltage_signals[cell]
                msg = next(m for m in db.messages if any(s.name == name for s in m.signals))
                self._stuck[name] = (t0, msg, None)
                self._stuck_msgs[msg.frame_id] = msg

    def apply(self, frames: Iterable[can.Message]) -> Iterator[can.Message]:
        s = self.spec
        rng = self.rng
        held: can.Message | None = None
        for msg in frames:
            if self._t0 is None:
                self._t0 = msg.timestamp
            rel = msg.timestamp - self._t0
            if any(t0 <= rel < t0 + d for t0, d in s.bus_gaps):
                self.counts["gap_dropped"] += 1
                continue
            if s.drop and rng.random() < s.drop:
                self.counts["dropped"] += 1
                continue
            if self._stuck and msg.arbitration_id in self._stuck_msgs:
                msg = self._apply_stuck(msg, rel)
            if s.corrupt and rng.random() < s.corrupt:
                msg = self._corrupt(msg)
            out = [msg]
            if s.duplicate and rng.random() < s.duplicate:
                self.counts["duplicated"] += 1
                out.append(copy.copy(msg))
            for m in out:
                if held is not None:
                    yield self._jitter(m)
                    yield self._jitter(held)
                    held = None
                elif s.reorder and rng.random() < s.reorder:
                    self.counts["reordered"] += 1
                    held = m
                else:
                    yield self._jitter(m)
        if held is not None:
            yield self._jitter(held)

    # -- individual faults -------------------------------------------------------------
    def _jitter(self, msg: can.Message) -> can.Message:
        if not self.spec.jitter_s:
            return msg
        msg = copy.copy(msg)
        # a serial bus delays frames but keeps their order
        ts = msg.timestamp + float(self.rng.uniform(0.0, self.spec.jitter_s))
        msg.timestamp = max(ts, self._last_ts)
        self._last_ts = msg.timestamp
        self.counts["jittered"] += 1
        return msg

    def _corrupt(self, msg: can.Message) -> can.Message:
        msg = copy.copy(msg)
        data = bytearray(msg.data)
        mode = self.spec.corrupt_mode
        if mode == "any":
            mode = "bitflip" if self.rng.random() < 0.5 else "dlc"
        if mode == "bitflip" and data:
            bit = int(self.rng.integers(0, 8 * len(data)))
            data[bit // 8] ^= 1 << (bit % 8)
            self.counts["corrupted_bitflip"] += 1
        else:
            if len(data) >= 8 or (len(data) > 1 and self.rng.random() < 0.5):
                data = data[:-1]
            else:
                data.append(int(self.rng.integers(0, 256)))
            self.counts["corrupted_dlc"] += 1
        msg.data = data
        msg.dlc = len(data)
        return msg

    def _apply_stuck(self, msg: can.Message, rel: float) -> can.Message:
        m = self._stuck_msgs[msg.arbitration_id]
        try:
            values = m.decode(bytes(msg.data), decode_choices=False, scaling=True)
        except Exception:  # noqa: BLE001 - leave undecodable frames alone
            return msg
        changed = False
        for name, (t0, _, frozen) in list(self._stuck.items()):
            if name not in values:
                continue
            if rel < t0:
                self._stuck[name] = (t0, m, values[name])  # remember the latest value before T0
                continue
            if frozen is None:
                frozen = values[name]
                self._stuck[name] = (t0, m, frozen)
            if values[name] != frozen:
                values[name] = frozen
                changed = True
        if not changed:
            return msg
        msg = copy.copy(msg)
        msg.data = bytearray(m.encode(values, scaling=True, padding=False, strict=False))
        self.counts["stuck"] += 1
        return msg
