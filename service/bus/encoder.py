""":class:`PackSnapshot` in, output CAN frames out (``dbc/socd_output.dbc``, cantools).

Per snapshot: one ``SOCD_CellSoc`` and one ``SOCD_CellParams`` frame per cell, one
``SOCD_PackSummary``, one ``SOCD_Status`` and one ``SOCD_PackUsable`` (the snapshot's pack
view; its valid bit 0 when there is none), then one ``SOCD_CellHealth`` per cell (capacity
and resistance growth in % of the profile's) when the snapshot carries ``health``.  A message
the output DBC lacks (a user's DBC from before it existed) is left out.  Values are converted
to wire units (SOC in %,
resistances in mΩ) and clamped into each signal's range; NaN goes out as the signal's
minimum with the cell's stale bit set.  ``encode`` never raises on bad values.

``decode_output(msg)`` is the inverse for tests and ``socd watch``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import can
import numpy as np

from service.bus.types import STATUS_FLAGS, PackSnapshot
from service.config import DEFAULT_OUTPUT_DBC, SocdConfig, load_dbc
from service.estimators.pack_view import PackView
from service.estimators.state_of_health import CellHealth

_WIRE_SCALE = {"r_ohm": 1e3, "r_ct": 1e3, "r_df": 1e3, "m": 1.0, "n": 1.0}  # SI -> wire units
_PARAM_SIGNALS = {"r_ohm": "SOCD_ROhm", "r_ct": "SOCD_RCt", "r_df": "SOCD_RDf", "m": "SOCD_M", "n": "SOCD_N"}
#: CellHealth field -> (signal, SI -> wire scale); the capacity σ goes out relative to the profile's capacity
_HEALTH_SIGNALS = {"capacity_rel": ("SOCD_CapacityPct", 100.0), "capacity_std_rel": ("SOCD_CapacityStdPct", 100.0),
                   "resistance_rel": ("SOCD_ResistancePct", 100.0)}


def flag_signal(name: str) -> str:
    """``"stale_cells"`` -> ``"SOCD_FlagStaleCells"``."""
    return "SOCD_Flag" + "".join(w.capitalize() for w in name.split("_"))


def _signal_range(sig) -> tuple[float, float]:
    """Physical range a signal can carry: its DBC min/max if given, else the raw range."""
    scale = float(sig.scale)
    offset = float(sig.offset)
    if sig.is_float:
        raw_lo, raw_hi = -3.4e38, 3.4e38
    elif sig.is_signed:
        raw_lo, raw_hi = -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    else:
        raw_lo, raw_hi = 0, (1 << sig.length) - 1
    lo, hi = sorted((raw_lo * scale + offset, raw_hi * scale + offset))
    if sig.minimum is not None:
        lo = max(lo, float(sig.minimum))
    if sig.maximum is not None:
        hi = min(hi, float(sig.maximum))
    return lo, hi


class _Out:
    """One output message: cantools Message + clamping ranges + a rolling counter."""

    def __init__(self, message, counter: str | None = None) -> None:
        self.message = message
        self.ranges = {s.name: _signal_range(s) for s in message.signals}
        self.counter = counter if counter in self.ranges else None
        self.counter_mod = 1 << message.get_signal_by_name(counter).length if self.counter else 1
        self.count = 0
        self.frame_id = message.frame_id
        self.is_extended = bool(message.is_extended_frame)

    def clamp(self, name: str, value: Any) -> float:
        lo, hi = self.ranges[name]
        try:
            v = float(value)
        except (TypeError, ValueError):
            return lo
        if not math.isfinite(v):
            return lo if v != math.inf else hi
        return hi if v > hi else max(v, lo)

    def frame(self, values: dict[str, Any], t_s: float) -> can.Message:
        data = {n: self.clamp(n, v) for n, v in values.items() if n in self.ranges}
        if self.counter:
            data[self.counter] = self.count
            self.count = (self.count + 1) % self.counter_mod
        for n in self.ranges:  # absent signals go out as their minimum (usually 0)
            data.setdefault(n, max(self.ranges[n][0], 0.0) if self.ranges[n][1] >= 0 else self.ranges[n][0])
        payload = self.message.encode(data, scaling=True, padding=False, strict=False)
        return can.Message(
            timestamp=t_s,
            arbitration_id=self.frame_id,
            is_extended_id=self.is_extended,
            data=payload,
            is_fd=len(payload) > 8,
        )


class OutputEncoder:
    """Encodes snapshots with the config's output DBC (frames in the order listed above)."""

    def __init__(self, config: SocdConfig | None = None, db=None) -> None:
        if db is None:
            db = config.output_db() if config is not None else load_dbc(DEFAULT_OUTPUT_DBC)
        self.db = db
        self.soc = _Out(db.get_message_by_name("SOCD_CellSoc"), "SOCD_SocCounter")
        self.params = _Out(db.get_message_by_name("SOCD_CellParams"), "SOCD_ParCounter")
        self.summary = _Out(db.get_message_by_name("SOCD_PackSummary"))
        self.status = _Out(db.get_message_by_name("SOCD_Status"), "SOCD_StatusCounter")
        try:
            self.usable: _Out | None = _Out(db.get_message_by_name("SOCD_PackUsable"), "SOCD_PackUsableCounter")
        except KeyError:  # a user's output DBC from before the message existed
            self.usable = None
        names = {m.name for m in db.messages}
        self.health = _Out(db.get_message_by_name("SOCD_CellHealth"), "SOCD_HlthCounter") \
            if "SOCD_CellHealth" in names else None
        self.max_cells = int(self.soc.ranges["SOCD_SocCellIndex"][1]) + 1
        self.errors = 0  # snapshots (or cells) that could not be encoded at all

    def encode(self, snapshot: PackSnapshot, *, cells: bool = True, params: bool = True) -> list[can.Message]:
        """All output frames for ``snapshot``; never raises (failures are counted in ``errors``)."""
        return list(self.frames(snapshot, cells=cells, params=params))

    def frames(self, snapshot: PackSnapshot, *, cells: bool = True, params: bool = True) -> Iterator[can.Message]:
        """:meth:`encode`'s frames one at a time, each encoded when it is taken: a caller on the
        event loop sends a few and yields, instead of holding the loop while hundreds of cells'
        frames are encoded."""
        t = float(snapshot.t_s) if snapshot.t_s is not None else 0.0
        try:
            soc = np.asarray(snapshot.soc, dtype=float).ravel()
            std = np.broadcast_to(np.asarray(snapshot.soc_std, dtype=float).ravel(), soc.shape)
            stale = np.broadcast_to(np.asarray(snapshot.stale, dtype=bool).ravel(), soc.shape)
        except Exception:  # noqa: BLE001
            self.errors += 1
            return
        n = min(soc.size, self.max_cells)
        if cells:
            for i in range(n):
                frame = self._counted(self.soc.frame, {
                    "SOCD_SocCellIndex": i,
                    "SOCD_Soc": soc[i] * 100.0,
                    "SOCD_SocStd": std[i] * 100.0,
                    "SOCD_SocStale": 1 if (stale[i] or not math.isfinite(soc[i])) else 0,
                }, t)
                if frame is not None:
                    yield frame
        if params:
            arrays = {}
            for key in _PARAM_SIGNALS:
                try:
                    arr = np.asarray(snapshot.params.get(key, np.nan), dtype=float).ravel()
                    arrays[key] = np.broadcast_to(arr, soc.shape) if arr.size in (1, soc.size) else None
                except Exception:  # noqa: BLE001
                    arrays[key] = None
            for i in range(n):
                values: dict[str, Any] = {"SOCD_ParCellIndex": i}
                for key, sig in _PARAM_SIGNALS.items():
                    a = arrays[key]
                    values[sig] = a[i] * _WIRE_SCALE[key] if a is not None else 0.0
                frame = self._counted(self.params.frame, values, t)
                if frame is not None:
                    yield frame
        pack_frames = [self._counted(self._summary, soc, stale, t), self._counted(self._status, snapshot, stale, t)]
        if self.usable is not None:
            pack_frames.append(self._counted(self._usable, self.usable, snapshot.pack, t))
        yield from (f for f in pack_frames if f is not None)
        if params and self.health is not None and snapshot.health is not None:
            yield from self._health(snapshot.health, n, soc.shape, t)

    def _counted(self, make: Callable[..., can.Message], *args: Any) -> can.Message | None:
        """``make(*args)``, or None with the failure counted in ``errors``."""
        try:
            return make(*args)
        except Exception:  # noqa: BLE001 - a value the DBC cannot carry must not stop the others
            self.errors += 1
            return None

    def _health(self, health: CellHealth, n: int, shape: tuple[int, ...], t: float) -> Iterator[can.Message]:
        """The SOCD_CellHealth frames, one cell at a time (as :meth:`frames`)."""
        arrays: dict[str, np.ndarray | None] = {}
        try:
            for key in _HEALTH_SIGNALS:
                arr = np.asarray(getattr(health, key), dtype=float).ravel()
                arrays[key] = np.broadcast_to(arr, shape) if arr.size in (1, shape[0]) else None
        except Exception:  # noqa: BLE001
            self.errors += 1
            return
        for i in range(n):
            values: dict[str, Any] = {"SOCD_HlthCellIndex": i}
            for key, (sig, scale) in _HEALTH_SIGNALS.items():
                a = arrays[key]
                values[sig] = a[i] * scale if a is not None else 0.0
            frame = self._counted(self.health.frame, values, t)
            if frame is not None:
                yield frame

    def _summary(self, soc: np.ndarray, stale: np.ndarray, t: float) -> can.Message:
        ok = np.isfinite(soc) & ~stale
        if not ok.any():
            ok = np.isfinite(soc)
        if not ok.any():
            return self.summary.frame({}, t)
        idx = np.flatnonzero(ok)
        vals = soc[idx]
        i_min, i_max = int(idx[np.argmin(vals)]), int(idx[np.argmax(vals)])
        return self.summary.frame({
            "SOCD_SocMin": soc[i_min] * 100.0,
            "SOCD_SocMean": float(vals.mean()) * 100.0,
            "SOCD_SocMax": soc[i_max] * 100.0,
            "SOCD_SocMinCell": i_min,
            "SOCD_SocMaxCell": i_max,
        }, t)

    @staticmethod
    def _usable(msg: _Out, view: PackView | None, t: float) -> can.Message:
        if view is None or not view.ok:
            return msg.frame({"SOCD_PackUsableValid": 0}, t)
        return msg.frame({
            "SOCD_UsableSoc": view.usable_soc * 100.0,
            "SOCD_RemainingEnergy": round(view.remaining_energy_wh),
            "SOCD_PackUsableValid": 1 if np.isfinite(view.usable_soc) else 0,
            "SOCD_ImbalanceAh": view.imbalance_ah,
            "SOCD_WeakestCell": view.weakest_cell,
        }, t)

    def _status(self, snapshot: PackSnapshot, stale: np.ndarray, t: float) -> can.Message:
        flags = dict(snapshot.status_flags or {})
        n_stale = int(snapshot.counters.get("stale_cells", int(stale.sum())))
        flags.setdefault("stale_cells", n_stale > 0)
        values: dict[str, Any] = {flag_signal(k): 1 if v else 0 for k, v in flags.items()}
        values["SOCD_FramesRejected"] = snapshot.counters.get("frames_rejected", 0)
        values["SOCD_StaleCells"] = n_stale
        return self.status.frame(values, t)


# ---------------------------------------------------------------------------------------
# decoding the outputs (tests, socd watch)
# ---------------------------------------------------------------------------------------
def decode_output(msg: can.Message, db=None) -> dict[str, Any]:
    """Decode one output frame: ``{"message": name, <signal>: value, ...}`` in wire units.

    For ``SOCD_Status`` also ``"flags"``: ``{flag_name: bool}`` with names as in
    :data:`STATUS_FLAGS`.  Returns ``{}`` for a frame that is not an output frame or does not
    decode (never raises).
    """
    db = db if db is not None else load_dbc(DEFAULT_OUTPUT_DBC)
    try:
        m = db.get_message_by_frame_id(msg.arbitration_id)
    except KeyError:
        return {}
    if bool(m.is_extended_frame) != bool(msg.is_extended_id):
        return {}
    try:
        values = m.decode(bytes(msg.data), decode_choices=False, scaling=True)
    except Exception:  # noqa: BLE001
        return {}
    out: dict[str, Any] = {"message": m.name, **values}
    if m.name == "SOCD_Status":
        out["flags"] = {
            f: bool(values.get(flag_signal(f), 0)) for f in STATUS_FLAGS if flag_signal(f) in values
        }
    return out
