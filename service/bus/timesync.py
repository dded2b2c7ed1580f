"""The time-sync signal: the sender's sample time carried on the bus itself.

A kernel CAN bus (SocketCAN ``vcan0``, ``can0``) stamps every frame when it arrives, so a
replay faster than real time arrives with time steps compressed by the replay speed.  When
``mapping.time_signal`` names a signal, the sender (``socd replay``) writes each sample's
time into it, in a frame sent once per sample before the sample's other frames, and the
decoder (:mod:`service.bus.decoder`) clocks the sample by that value instead of by arrival.

The value on the wire is the time modulo the signal's span: an unsigned integer signal of
``L`` bits at ``scale`` s/bit repeats every ``2**L * scale`` seconds.  The shipped
``BMS_TimeSync.BMS_SampleTime`` is 32 bits of 1 ms, a period of 2^32 ms = 49.7 days, longer
than any drive; the receiver unwraps the count by taking the time nearest the previous one,
so even a replay looping for longer keeps a continuous clock.  A signed or floating-point
signal does not wrap: a time outside its range cannot be sent.

>>> import cantools
>>> from pathlib import Path
>>> db = cantools.database.load_file(Path(__file__).parents[2] / "dbc" / "bms_pack.dbc")
>>> ts = TimeSignal.find(db, "BMS_SampleTime")
>>> ts.period_s
4294967.296
>>> ts.wire_value(4294967.296 + 12.3456)
12.346
>>> ts.unwrap(0.5, near_s=4294967.0)
4294967.796
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


class TimeSignalError(ValueError):
    """The named time signal cannot carry a time (missing, multiplexed, or out of range)."""


@dataclass(frozen=True)
class TimeSignal:
    """One DBC signal that carries the sample time, in seconds."""

    message: Any  # cantools Message holding the signal
    signal: Any  # cantools Signal
    #: seconds after which the value on the wire repeats (None: the signal does not wrap)
    period_s: float | None

    @property
    def name(self) -> str:
        return str(self.signal.name)

    @classmethod
    def find(cls, db: Any, name: str) -> TimeSignal:
        """The signal ``name`` of the cantools database ``db``; :class:`TimeSignalError` if it
        is missing or multiplexed (a time must be in every frame of its message)."""
        for m in db.messages:
            for s in m.signals:
                if s.name == name:
                    if s.multiplexer_ids or s.is_multiplexer:
                        raise TimeSignalError(f"time signal {name!r} is multiplexed in {m.name}; "
                                              "it must be in every frame of its message")
                    return cls(m, s, _period_s(s))
        raise TimeSignalError(f"time signal {name!r} is not in the DBC")

    def wire_value(self, t_s: float) -> float:
        """The value to encode for time ``t_s``: reduced modulo the period, rounded to the
        signal's resolution.  :class:`TimeSignalError` for a time a non-wrapping signal cannot hold."""
        s = self.signal
        scale, offset = float(s.scale), float(s.offset)
        raw = round((float(t_s) - offset) / scale)
        if self.period_s is not None:
            raw %= 1 << s.length
        value = raw * scale + offset
        lo = s.minimum if s.minimum is not None else -math.inf
        hi = s.maximum if s.maximum is not None else math.inf
        if not (math.isfinite(value) and lo - abs(scale) / 2 <= value <= hi + abs(scale) / 2):
            raise TimeSignalError(f"time {t_s:g} s does not fit {self.name} ({lo:g}..{hi:g} s)")
        return round(value, 9)

    def unwrap(self, value_s: float, near_s: float | None) -> float:
        """The time whose wire value is ``value_s`` nearest ``near_s`` (the previous time);
        ``value_s`` itself when there is no previous time or the signal does not wrap."""
        p = self.period_s
        if p is None or near_s is None or not (math.isfinite(value_s) and math.isfinite(near_s)):
            return value_s
        return round(value_s + p * round((near_s - value_s) / p), 9)


def _period_s(signal: Any) -> float | None:
    """``2**length * scale`` for an unsigned integer signal, else None (it does not wrap)."""
    if signal.is_float or signal.is_signed or not float(signal.scale) > 0:
        return None
    return (1 << int(signal.length)) * float(signal.scale)
