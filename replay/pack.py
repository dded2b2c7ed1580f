"""One cell's recording expanded to a pack of N cells and encoded as BMS frames.

Each cell ``i`` gets a seeded spread of capacity, ohmic resistance and start SOC
(:class:`SpreadSpec`) and its terminal voltage is the recorded one moved by the
difference of OCVs and of ohmic drops:

    V_i(t) = V_rec(t) + OCV(SOC_i(t), T) - OCV(SOC_ref(t), T) - ΔR_i · I(t)

with ``SOC_ref`` coulomb-counted (backward zero-order hold, as the estimator does) from a
start SOC read off the first rest voltage through the profile's OCV table (or given), and
``SOC_i`` counted the same way with the cell's own capacity and start SOC.  The per-cell
truth SOC is kept in :class:`PackRecording` so a run can be scored.

Frames are generated through the config's *mapping* and the input DBC, so any DBC the
decoder can read, the replay can write: per sample, the time-sync frame when the mapping
names a ``time_signal`` (carrying the sample's time, :mod:`service.bus.timesync`), every
voltage/temperature frame (each multiplexer value), then the pack-current frame, all stamped
with the sample's recording time (+ ``time_offset_s``); rolling counters advance per frame of
each ID.  The time-sync frame is what keeps the recording's time on a kernel bus, which
restamps frames on arrival.
"""

from __future__ import annotations

import csv
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from service.bus.timesync import TimeSignal
from service.cell.profile import CellProfile
from service.cell.units import SECONDS_PER_HOUR
from service.config import SocdConfig
from service.recording import Recording

#: signals the generator fills with the pack voltage when they are not mapped
_PACK_VOLTAGE_NAME = re.compile(r"pack.?volt|vdc|vbat|vpack", re.IGNORECASE)


@dataclass(frozen=True)
class SpreadSpec:
    """Cell-to-cell spread (σ of a normal distribution, clipped at ±3σ).

    ``capacity`` and ``resistance`` are relative (0.02 = 2 %), ``soc`` absolute (0.02 =
    2 % SOC), ``temperature_c`` absolute per sensor (°C).  A cell's start SOC stays in
    [0, 1]: a pack that starts full has no cell above full.
    """

    capacity: float = 0.0
    resistance: float = 0.0
    soc: float = 0.0
    temperature_c: float = 0.0


@dataclass
class PackRecording:
    """What was played: per-sample pack inputs and the per-cell truth."""

    time_s: np.ndarray  # [T] frame timestamps of the samples (recording time + offset)
    current_a: np.ndarray  # [T] positive = discharge
    voltage_v: np.ndarray  # [T, N]
    temperature_c: np.ndarray  # [T, N] at each cell (its sensor's value)
    truth_soc: np.ndarray  # [T, N]
    soc_ref: np.ndarray  # [T] the recorded cell's SOC
    capacity_ah: np.ndarray  # [N]
    delta_r_ohm: np.ndarray  # [N]
    #: the recorded cell's true SOC at the first sample and where it came from
    start: StartSoc
    sensor_temperature_c: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # [T, S]
    source: str = ""
    #: measured values (cell voltages, temperatures, current) beyond their input-DBC signal's declared
    #: minimum/maximum, sent clipped to it, per signal; counted as the frames are built (lazy: as played)
    clipped: Counter = field(default_factory=Counter)
    #: measured values that encode as their signal's offset though they differ from it, and those
    #: that differ at all, per signal (:class:`FrameBuilder`)
    zeroed: Counter = field(default_factory=Counter)
    nonzero: Counter = field(default_factory=Counter)

    @property
    def n_cells(self) -> int:
        return int(self.truth_soc.shape[1])

    def __len__(self) -> int:
        return int(self.time_s.size)

    def write_truth_csv(self, path: str | Path) -> None:
        """``time_s,current_a,soc_ref,soc_0..soc_{N-1}`` (SOC in [0, 1])."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["time_s", "current_a", "soc_ref", *[f"soc_{i}" for i in range(self.n_cells)]])
            for k in range(len(self)):
                w.writerow([f"{self.time_s[k]:.6f}", f"{self.current_a[k]:.5f}", f"{self.soc_ref[k]:.6f}",
                            *(f"{x:.6f}" for x in self.truth_soc[k])])


#: a rest (current within 2 % of 1C) shorter than this leaves a cold cell's voltage minutes from its OCV:
#: a truth placed from it may be a few % off, and the demo says so
SETTLED_REST_S = 300.0


@dataclass(frozen=True)
class StartSoc:
    """The truth's SOC at a recording's first sample and where it came from (``source``, for the
    user); ``settled``: False where it was read from a voltage still relaxing (a few % off)."""

    soc: float
    source: str
    settled: bool = True

    def caution(self) -> str | None:
        """What a user should know of a start read from a voltage still relaxing, or None."""
        if self.settled:
            return None
        return (f"the truth starts at {100 * self.soc:.1f} % SOC, {self.source}, where the voltage was still "
                "relaxing: the truth and every SOC error against it may be a few % off; give --soc0 (1 if the "
                "recording starts at the end of a full charge)")


def known_start(path: Path) -> StartSoc | None:
    """The truth's start socd knows for a recording it ships (the bundled drive starts at the end of a
    CC-CV charge, which its OCV, read a second into its first rest, puts a few % lower), else None."""
    from service.assets import bundled_recording

    if Path(path).resolve() == bundled_recording().resolve():
        return StartSoc(1.0, "as the bundled drive starts at the end of a CC-CV charge (service/data/README.md)")
    return None


def estimate_start_soc(recording: Recording, profile: CellProfile, rest_current_a: float | None = None) -> StartSoc:
    """SOC at the first sample from the first (near-)rest voltage (the end of the rest the recording
    opens with, if it does), counted back to t0; settled when the current had rested
    :data:`SETTLED_REST_S` there (an opening rest counts from the first sample: what came before is
    unknown).  A later, longer rest is not used: counting back to the start over a drive with the
    profile's capacity moves the start as much as the relaxation does."""
    table = profile.ocv_table()
    capacity = profile.effective_capacity_ah
    limit = rest_current_a if rest_current_a is not None else 0.02 * capacity
    t = recording.time_s
    at_rest = np.abs(recording.current_a) <= limit
    last_load = np.maximum.accumulate(np.where(at_rest, -1, np.arange(at_rest.size)))
    rested_s = t - np.where(last_load >= 0, t[np.maximum(last_load, 0)], t[0])
    rest = np.flatnonzero(at_rest)
    k = int(rest[0]) if rest.size else 0
    if k == 0 and at_rest[0]:  # the rest the recording opens with: its end is the most relaxed voltage in it
        k = int(np.argmin(at_rest)) - 1 if not at_rest.all() else at_rest.size - 1
    soc_k = float(table.soc_from_ocv(recording.voltage_v[k], recording.temperature_c[k]))
    dq = recording.current_a * recording.dt_s()  # backward ZOH
    soc0 = float(np.clip(soc_k + float(dq[1:k + 1].sum()) / (SECONDS_PER_HOUR * capacity), 0.0, 1.0))
    where = f"the OCV at {t[k] - t[0]:.0f} s, {rested_s[k]:.0f} s into a rest" if at_rest[k] else \
        f"the OCV at the first sample, under {recording.current_a[0]:.3g} A (the recording has no rest)"
    return StartSoc(soc0, f"read from {where}, counted back to the start",
                    bool(at_rest[k] and rested_s[k] >= SETTLED_REST_S))


def truth_start(recording: Recording, profile: CellProfile, start_soc: float | StartSoc | None) -> StartSoc:
    """The replay truth's start: ``start_soc`` given (a :class:`StartSoc` as it is, with the caller's
    account of where it came from), else the recording's own ``soc_true``, else
    :func:`estimate_start_soc`."""
    if isinstance(start_soc, StartSoc):
        return start_soc
    if start_soc is not None:
        return StartSoc(float(start_soc), "given (--soc0)")
    if recording.soc_true is not None and np.isfinite(recording.soc_true[0]):
        # a recorded truth beats an OCV reading
        return StartSoc(float(np.clip(recording.soc_true[0], 0.0, 1.0)), "the recording's soc_true")
    return estimate_start_soc(recording, profile)


def expand_pack(
    recording: Recording,
    profile: CellProfile,
    n_cells: int,
    spread: SpreadSpec | None = None,
    seed: int = 0,
    start_soc: float | StartSoc | None = None,
    sensor_of_cell: np.ndarray | None = None,
    time_offset_s: float = 0.0,
) -> PackRecording:
    """Per-cell voltages and truth SOC for a pack built from one recorded cell."""
    spread = spread or SpreadSpec()
    rng = np.random.default_rng(seed)

    def draw(sigma: float, size: int) -> np.ndarray:
        if sigma <= 0:
            return np.zeros(size)
        return np.clip(rng.standard_normal(size), -3, 3) * sigma

    d_cap, d_res, d_soc = draw(spread.capacity, n_cells), draw(spread.resistance, n_cells), draw(spread.soc, n_cells)
    sensor_of_cell = np.zeros(n_cells, dtype=int) if sensor_of_cell is None else np.asarray(sensor_of_cell)
    n_sensors = int(sensor_of_cell.max()) + 1
    d_temp = draw(spread.temperature_c, n_sensors)

    capacity = profile.effective_capacity_ah
    cap_i = capacity * (1.0 + d_cap)
    start = truth_start(recording, profile, start_soc)
    soc0 = start.soc
    i = recording.current_a
    q_ah = np.cumsum(i * recording.dt_s()) / SECONDS_PER_HOUR  # backward ZOH, first step 0
    soc_ref = soc0 - q_ah / capacity
    # a cell cannot start above full or below empty (DESIGN: SOC in [0, 1])
    soc0_i = np.clip(soc0 + d_soc, 0.0, 1.0)
    truth = soc0_i[None, :] - q_ah[:, None] / cap_i[None, :]

    sensor_t = recording.temperature_c[:, None] + d_temp[None, :]
    temp_cell = sensor_t[:, sensor_of_cell]
    table = profile.ocv_table()
    r_ohm = profile.parameters_at(recording.temperature_c).r_ohm  # [T]
    delta_r = d_res  # relative; absolute ΔR_i(t) = r_ohm(T(t)) * d_res_i
    ocv_ref = table.ocv(soc_ref, recording.temperature_c)
    volt = (recording.voltage_v[:, None] + table.ocv(truth, temp_cell) - ocv_ref[:, None]
            - (r_ohm[:, None] * delta_r[None, :]) * i[:, None])
    return PackRecording(
        time_s=recording.time_s + float(time_offset_s),
        current_a=i.copy(),
        voltage_v=volt,
        temperature_c=temp_cell,
        truth_soc=truth,
        soc_ref=soc_ref,
        capacity_ah=cap_i,
        delta_r_ohm=float(np.median(r_ohm)) * delta_r,
        sensor_temperature_c=sensor_t,
        source=str(recording.path),
        start=start,
    )


# ---------------------------------------------------------------------------------------
# frame generation through the mapping and the DBC
# ---------------------------------------------------------------------------------------
@dataclass
class _Template:
    message: object
    mux_signal: str | None
    mux_value: int | None
    volts: list[tuple[str, int]]  # (signal, cell)
    temps: list[tuple[str, int]]  # (signal, sensor)
    current: str | None
    counter: str | None
    time: str | None
    fixed: dict[str, float]
    pack_voltage: list[str]
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: per measured signal, (scale, offset): a value within half a step of the offset encodes as it
    steps: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def measured(self) -> set[str]:
        """The signals carrying the pack's measured values (clipping them is counted)."""
        return {n for n, _ in self.volts} | {n for n, _ in self.temps} | ({self.current} if self.current else set())


class FrameBuilder:
    """Turns pack values into BMS frames with the config's mapping and input DBC."""

    def __init__(self, config: SocdConfig, db=None) -> None:
        self.config = config
        self.db = db if db is not None else config.input_db()
        mp = config.mapping
        volt_of = {s: i for i, s in enumerate(mp.cell_voltage_signals)}
        temp_of = {t.signal: k for k, t in enumerate(mp.temperature_signals)}
        self.current_divisor = float(mp.current_sign) * float(mp.current_scale)
        self.time_signal = TimeSignal.find(self.db, mp.time_signal) if mp.time_signal is not None else None
        time_name = self.time_signal.name if self.time_signal is not None else None
        #: frames carrying the time (first in a sample), the other mapped frames, the current frame(s) (last)
        self.time_templates: list[_Template] = []
        self.templates: list[_Template] = []
        self.current_templates: list[_Template] = []
        self._counts: dict[int, int] = {}
        self._mods: dict[int, int] = {}
        #: measured values clipped to their signal's range, per signal
        self.clipped: Counter = Counter()
        #: measured values that differ from their signal's offset by less than half its step, so
        #: encode as the offset (a current scaled a thousand times too small reads 0 A), per signal,
        #: and the measured values that differ from it at all
        self.zeroed: Counter = Counter()
        self.nonzero: Counter = Counter()
        for m in self.db.messages:
            names = [s.name for s in m.signals]
            mapped = [n for n in names if n in volt_of or n in temp_of or n in (mp.current_signal, time_name)]
            if not mapped:
                continue
            counter = mp.counter_signals.get(m.name)
            counter = counter if counter in names else None
            if counter:
                self._mods[m.frame_id] = 1 << m.get_signal_by_name(counter).length
            muxers = [s for s in m.signals if s.is_multiplexer]
            mux = muxers[0] if muxers else None
            groups: dict[int | None, list[str]] = {}
            for s in m.signals:
                if s.is_multiplexer:
                    continue
                ids = s.multiplexer_ids or [None]
                for v in ids:
                    groups.setdefault(v, []).append(s.name)
            plain = groups.pop(None, [])
            keys = sorted(groups) if groups else [None]
            for v in keys:
                sigs = plain + groups.get(v, [])
                if not any(n in volt_of or n in temp_of or n in (mp.current_signal, time_name) for n in sigs):
                    continue
                t = _Template(
                    message=m, mux_signal=mux.name if (mux is not None and v is not None) else None, mux_value=v,
                    volts=[(n, volt_of[n]) for n in sigs if n in volt_of],
                    temps=[(n, temp_of[n]) for n in sigs if n in temp_of],
                    current=mp.current_signal if mp.current_signal in sigs else None,
                    counter=counter if counter in sigs else None,
                    time=time_name if time_name in sigs else None,
                    fixed={}, pack_voltage=[],
                )
                for n in sigs:
                    if n in volt_of or n in temp_of or n in (mp.current_signal, counter, time_name):
                        continue
                    if _PACK_VOLTAGE_NAME.search(n):
                        t.pack_voltage.append(n)
                    else:
                        sig = m.get_signal_by_name(n)
                        lo = sig.minimum if sig.minimum is not None else None
                        t.fixed[n] = 0.0 if lo is None or lo <= 0 else lo
                for sig in m.signals:  # a value beyond the bits themselves stops the replay (_frame)
                    if sig.minimum is not None and sig.maximum is not None and sig.maximum > sig.minimum:
                        t.ranges[sig.name] = (float(sig.minimum), float(sig.maximum))
                    if sig.name in t.measured and sig.scale:
                        t.steps[sig.name] = (abs(float(sig.scale)), float(sig.offset))
                (self.current_templates if t.current else self.time_templates if t.time else self.templates).append(t)

    def _frame(self, t: _Template, values: dict[str, float], ts: float) -> can.Message:
        m = t.message
        if t.mux_signal is not None:
            values[t.mux_signal] = t.mux_value
        if t.counter is not None:
            c = self._counts.get(m.frame_id, 0)
            values[t.counter] = c
            self._counts[m.frame_id] = (c + 1) % self._mods[m.frame_id]
        for n, v in t.fixed.items():
            values.setdefault(n, v)
        ranges = t.ranges
        for n, v in values.items():
            r = ranges.get(n)
            if r is not None and not r[0] <= v <= r[1]:
                values[n] = r[0] if v < r[0] else r[1]
                if n in t.measured:
                    self.clipped[n] += 1
        for n, (step, offset) in t.steps.items():
            if n in values and values[n] != offset:
                self.nonzero[n] += 1
                self.zeroed[n] += abs(values[n] - offset) < step / 2
        try:
            data = m.encode(values, scaling=True, padding=False, strict=False)
        except (ValueError, OverflowError) as exc:  # a signal too narrow for its own declared range
            raise ValueError(f"message {m.name} cannot carry its values ({exc})") from None
        return can.Message(timestamp=ts, arbitration_id=m.frame_id, is_extended_id=bool(m.is_extended_frame),
                           data=data, is_fd=len(data) > 8)

    @property
    def sample_templates(self) -> list[_Template]:
        """The frames of one sample, in the order they are sent."""
        return self.time_templates + self.templates + self.current_templates

    def frames_for_sample(self, ts: float, current_a: float, voltage_v: np.ndarray,
                          sensor_c: np.ndarray) -> list[can.Message]:
        """The time-sync frame (when mapped), voltage/temperature frames (every multiplexer
        value), then the current frame(s)."""
        out = []
        pack_v = float(np.nansum(voltage_v))
        for t in self.sample_templates:
            values: dict[str, float] = {}
            if t.time is not None and self.time_signal is not None:
                values[t.time] = self.time_signal.wire_value(ts)
            for n, i in t.volts:
                values[n] = float(voltage_v[i])
            for n, k in t.temps:
                values[n] = float(sensor_c[k])
            if t.current:
                values[t.current] = current_a / self.current_divisor
            for n in t.pack_voltage:
                values[n] = pack_v
            out.append(self._frame(t, values, ts))
        return out


def iter_pack_frames(pack: PackRecording, builder: FrameBuilder) -> Iterator[can.Message]:
    for k in range(len(pack)):
        yield from builder.frames_for_sample(
            float(pack.time_s[k]), float(pack.current_a[k]), pack.voltage_v[k], pack.sensor_temperature_c[k]
        )


def pack_frames(
    recording: Recording,
    config: SocdConfig,
    profile: CellProfile,
    n_cells: int | None = None,
    spread: SpreadSpec | None = None,
    seed: int = 0,
    *,
    start_soc: float | StartSoc | None = None,
    time_offset_s: float = 0.0,
    lazy: bool = False,
    db=None,
) -> tuple[list[can.Message] | Iterator[can.Message], PackRecording]:
    """Frames for ``recording`` expanded to ``n_cells`` (default ``config.pack.n_cells``).

    ``n_cells`` must not exceed the config's mapped cells (the DBC has no signal for more);
    with fewer, the config is narrowed to the first ``n_cells`` cells.  With ``lazy`` the
    frames come as an iterator (long recordings start at once).
    """
    n_cells = config.pack.n_cells if n_cells is None else int(n_cells)
    if not 1 <= n_cells <= config.pack.n_cells:
        raise ValueError(f"n_cells={n_cells} but the config maps {config.pack.n_cells} cells")
    if n_cells != config.pack.n_cells:
        config = narrow_config(config, n_cells)
    sensor_of_cell = np.array(config.mapping.sensor_of_cell(n_cells))
    pack = expand_pack(recording, profile, n_cells, spread, seed, start_soc, sensor_of_cell, time_offset_s)
    n_sensors = len(config.mapping.temperature_signals)
    if pack.sensor_temperature_c.shape[1] < n_sensors:  # sensors covering no cell of a narrowed pack
        extra = np.repeat(pack.sensor_temperature_c[:, :1], n_sensors - pack.sensor_temperature_c.shape[1], 1)
        pack.sensor_temperature_c = np.hstack([pack.sensor_temperature_c, extra])
    builder = FrameBuilder(config, db)
    pack.clipped, pack.zeroed, pack.nonzero = builder.clipped, builder.zeroed, builder.nonzero
    frames = iter_pack_frames(pack, builder)
    return (frames if lazy else list(frames)), pack


def first_outside_unit(truth_soc: np.ndarray, margin: float = 0.0) -> tuple[int, int] | None:
    """``(sample, cell)`` where a cell's true SOC (``[T, N]``) first leaves [-margin, 1 + margin], or None."""
    outside = (truth_soc < -margin) | (truth_soc > 1.0 + margin)
    rows = np.flatnonzero(outside.any(axis=1))
    if rows.size == 0:
        return None
    k = int(rows[0])
    return k, int(np.flatnonzero(outside[k])[0])


def narrow_config(config: SocdConfig, n_cells: int) -> SocdConfig:
    """The same config for the first ``n_cells`` cells (sensors covering none are dropped)."""
    mp = config.mapping
    temps = []
    for t in mp.temperature_signals:
        cells = [c for c in t.cells if c < n_cells]
        if cells:
            temps.append({"signal": t.signal, "cells": cells})
    data = config.model_dump()
    data["pack"]["n_cells"] = n_cells
    m = data["mapping"]
    m.update(cell_voltage_signals=mp.cell_voltage_signals[:n_cells], temperature_signals=temps, cells=[],
             cell_voltage_pattern=None, temperature_pattern=None)
    return config.__class__.model_construct(**{
        **{k: getattr(config, k) for k in config.__class__.model_fields},
        "pack": config.pack.__class__(n_cells=n_cells),
        "mapping": mp.__class__.model_validate(m),
    })
