#!/usr/bin/env python3
"""Write the shipped DBC files: the BMS input bus and the estimator's output frames.

    python dbc/generate_dbc.py --cells 96 --temps 24

``bms_pack.dbc`` models a typical BMS bus (Intel byte order, scaled integers, rolling
counters, multiplexed cell data):

* ``BMS_PackStatus`` 0x100, 10 ms: ``BMS_PackCurrent`` int16, 0.05 A/bit, **positive =
  charge** (as many BMSs send it; the config's ``current_sign = -1`` flips it),
  ``BMS_PackVoltage`` 0.01 V/bit, ``BMS_PackCounter`` 4-bit rolling counter.
* ``BMS_CellVoltages`` 0x110, 100 ms: mux ``BMS_CellVoltMux`` = block index; block ``k``
  carries cells ``4k+1 .. 4k+4`` as ``BMS_Cell001_V`` .. (13 bit, 1 mV/bit, 0-8.191 V),
  plus ``BMS_CellVoltCounter`` (4 bit, incremented on every frame of this ID).
* ``BMS_CellTemps`` 0x120, 1000 ms: mux ``BMS_CellTempMux``; block ``k`` carries sensors
  ``4k+1 .. 4k+4`` as ``BMS_Temp01_C`` .. (12 bit signed, 0.1 °C/bit), plus a counter.
* ``BMS_TimeSync`` 0x0F0, once per sample, before the sample's other frames:
  ``BMS_SampleTime``, the sender's sample time as an unsigned 32-bit count of milliseconds.
  A kernel bus stamps frames on arrival, so a replay faster than real time needs the time on
  the bus itself (``mapping.time_signal``, :mod:`service.bus.timesync`).  1 ms resolves any
  BMS sample period; 32 bits wrap after 2^32 ms = 49.7 days, longer than any drive, and the
  receiver unwraps the count (it takes the time nearest the previous one), so a replay that
  loops for longer keeps a continuous clock.  0x0F0 wins arbitration over the sample's
  other frames on a real bus, as it is sent before them.

``socd_output.dbc`` (extended IDs, sender SOCD, classic 8-byte frames):

* ``SOCD_CellSoc`` 0x18FF50E5: mux ``SOCD_SocCellIndex`` (0-based cell), ``SOCD_Soc``
  (0.01 %/bit), ``SOCD_SocStd`` (0.01 %/bit), ``SOCD_SocCounter``.
* ``SOCD_CellParams`` 0x18FF51E5: mux ``SOCD_ParCellIndex``, ``SOCD_ROhm``/``SOCD_RCt``/
  ``SOCD_RDf`` (0.1 mΩ/bit), ``SOCD_M``/``SOCD_N`` (0.004/bit), ``SOCD_ParCounter``.
* ``SOCD_PackSummary`` 0x18FF52E5: min/mean/max SOC (0.01 %/bit), cell index of min/max.
* ``SOCD_Status`` 0x18FF53E5: a 32-bit status word made of named flag bits
  (``SOCD_Flag*``), frames rejected (saturating), stale cells, rolling counter.
* ``SOCD_PackUsable`` 0x18FF54E5: usable SOC (0.01 %/bit, limited by the weakest cell in
  each direction), remaining energy (1 Wh/bit), a valid bit, imbalance (1 mAh/bit), the
  weakest cell's index, rolling counter (:mod:`service.estimators.pack_view`).
* ``SOCD_CellHealth`` 0x18FF55E5: mux ``SOCD_HlthCellIndex``, ``SOCD_CapacityPct`` (estimated
  capacity / the profile's, 0.01 %/bit), ``SOCD_CapacityStdPct`` (its σ, 0.01 %/bit),
  ``SOCD_ResistancePct`` (R / R_nominal, 0.1 %/bit), ``SOCD_HlthCounter``.

The user-DBC example (``configs/user_dbc_example/acme_bms.dbc``) is written by
``--user-example``: different IDs, names, byte order and layout, to prove a user's own
DBC works by editing the config's mapping only.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cantools
from cantools.database import Database, Message, Node, Signal
from cantools.database.conversion import BaseConversion

from service.cell.profile import FIT_TEMPERATURE_MARGIN_K

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

CELLS_PER_VOLT_FRAME = 4
#: the time-sync message: a free standard ID below the sample's other frames (wins arbitration)
TIME_SYNC_FRAME_ID = 0x0F0
TIME_SYNC_RESOLUTION_S = 0.001
SENSORS_PER_TEMP_FRAME = 4
MAX_OUTPUT_CELLS = 256  # 8-bit cell index mux in the output frames

# bit order of the status word; must match service.bus.types.STATUS_FLAGS
STATUS_FLAGS = (
    ("stale_cells", "one or more cells have stale/missing/invalid inputs"),
    ("checkpoint_restored", "estimator state was restored from a checkpoint at start"),
    ("ocv_init", "SOC was initialised from OCV (rest voltage), not a checkpoint"),
    ("filter_reset", "a diverging filter was re-initialised since the last status frame"),
    ("bus_error", "CAN bus error or bus-off; reconnecting"),
    ("zenoh_down", "Zenoh session is down"),
    ("publish_drops", "output queue overflowed; publications were dropped"),
    ("diverged", "a filter's normalised innovation exceeded the divergence threshold"),
    ("param_clamped", "an identified parameter hit its physical bound"),
    ("no_current", "no pack-current frame within stale_after_s"),
    ("counter_errors", "rolling-counter jumps seen since the last status frame"),
    ("decode_errors", "frames rejected (DLC/decode/range/NaN) since the last status frame"),
    ("checkpoint_corrupt", "a checkpoint was found unusable at start; SOC initialised from OCV instead"),
    ("clock_reanchored", "the input frames' clock jumped and the decoder re-anchored on it"),
    ("state_aged", "the restored state was older than checkpoint.max_age_s; its SOC sigma was widened"),
    ("temperature_beyond_fit", (f"a cell reads more than {FIT_TEMPERATURE_MARGIN_K:g} K outside the temperatures its "
                                "profile was fitted at: its parameters are extrapolated there and its SOC sigma "
                                "does not allow for that")),
)


def camel(snake: str) -> str:
    return "".join(w.capitalize() for w in snake.split("_"))


def _sig(name, start, length, *, signed=False, scale=1.0, offset=0.0, minimum=None, maximum=None,
         unit=None, comment=None, mux_ids=None, mux_signal=None, is_mux=False, order="little_endian",
         receivers=None):
    if minimum is None or maximum is None:
        raw_min = -(1 << (length - 1)) if signed else 0
        raw_max = (1 << (length - 1)) - 1 if signed else (1 << length) - 1
        minimum = raw_min * scale + offset if minimum is None else minimum
        maximum = raw_max * scale + offset if maximum is None else maximum
    return Signal(
        name=name,
        start=start,
        length=length,
        byte_order=order,
        is_signed=signed,
        conversion=BaseConversion.factory(scale=scale, offset=offset),
        minimum=round(minimum, 6),
        maximum=round(maximum, 6),
        unit=unit,
        comment=comment,
        is_multiplexer=is_mux,
        multiplexer_ids=mux_ids,
        multiplexer_signal=mux_signal,
        receivers=receivers or [],
    )


# ---------------------------------------------------------------------------------------
# input: the BMS bus
# ---------------------------------------------------------------------------------------
def bms_database(n_cells: int = 96, n_temps: int = 24) -> Database:
    rx = ["SOCD"]
    pack = Message(
        frame_id=0x100,
        name="BMS_PackStatus",
        length=8,
        cycle_time=10,
        senders=["BMS"],
        comment="Pack current and voltage; the estimator's sample clock.",
        signals=[
            _sig("BMS_PackCurrent", 0, 16, signed=True, scale=0.05, unit="A", receivers=rx,
                 comment="Pack current, positive = CHARGE (flip with mapping.current_sign = -1)."),
            _sig("BMS_PackVoltage", 16, 16, scale=0.01, unit="V", receivers=rx,
                 comment="Pack terminal voltage."),
            _sig("BMS_PackCounter", 32, 4, receivers=rx,
                 comment="Rolling counter, +1 per frame, modulo 16."),
        ],
    )

    n_vblocks = math.ceil(n_cells / CELLS_PER_VOLT_FRAME)
    vsignals = [
        _sig("BMS_CellVoltMux", 0, 8, is_mux=True, maximum=n_vblocks - 1, minimum=0, receivers=rx,
             comment=f"Block index k: cells {CELLS_PER_VOLT_FRAME}k+1 .. {CELLS_PER_VOLT_FRAME}k+"
                     f"{CELLS_PER_VOLT_FRAME}."),
        _sig("BMS_CellVoltCounter", 8, 4, receivers=rx,
             comment="Rolling counter, +1 per frame of this ID (any block), modulo 16."),
    ]
    for cell in range(n_cells):
        block, slot = divmod(cell, CELLS_PER_VOLT_FRAME)
        vsignals.append(
            _sig(f"BMS_Cell{cell + 1:03d}_V", 12 + 13 * slot, 13, scale=0.001, unit="V",
                 mux_ids=[block], mux_signal="BMS_CellVoltMux", receivers=rx,
                 comment=f"Cell {cell + 1} voltage (1 mV/bit).")
        )
    volts = Message(frame_id=0x110, name="BMS_CellVoltages", length=8, cycle_time=100,
                    senders=["BMS"], signals=vsignals,
                    comment="Multiplexed cell voltages, 4 cells a frame.")

    n_tblocks = math.ceil(n_temps / SENSORS_PER_TEMP_FRAME)
    tsignals = [
        _sig("BMS_CellTempMux", 0, 8, is_mux=True, minimum=0, maximum=n_tblocks - 1, receivers=rx,
             comment="Block index k: sensors 4k+1 .. 4k+4."),
        _sig("BMS_CellTempCounter", 8, 4, receivers=rx,
             comment="Rolling counter, +1 per frame of this ID (any block), modulo 16."),
    ]
    for sensor in range(n_temps):
        block, slot = divmod(sensor, SENSORS_PER_TEMP_FRAME)
        tsignals.append(
            _sig(f"BMS_Temp{sensor + 1:02d}_C", 12 + 12 * slot, 12, signed=True, scale=0.1, unit="degC",
                 mux_ids=[block], mux_signal="BMS_CellTempMux", receivers=rx,
                 comment=f"Temperature sensor {sensor + 1} (0.1 degC/bit).")
        )
    temps = Message(frame_id=0x120, name="BMS_CellTemps", length=8, cycle_time=1000,
                    senders=["BMS"], signals=tsignals,
                    comment="Multiplexed cell temperatures, 4 sensors a frame.")
    sync = Message(
        frame_id=TIME_SYNC_FRAME_ID,
        name="BMS_TimeSync",
        length=4,
        cycle_time=10,
        senders=["BMS"],
        comment="The sender's sample time, sent once per sample before the sample's other frames, so a "
                "receiver clocks samples by it instead of by arrival (a replay faster than real time onto "
                "a kernel bus). Unsigned 32-bit count of ms: wraps after 2^32 ms (49.7 days); receivers "
                "unwrap it to the time nearest the previous one.",
        signals=[
            _sig("BMS_SampleTime", 0, 32, scale=TIME_SYNC_RESOLUTION_S, unit="s", receivers=rx,
                 comment="Sample time, 1 ms/bit, modulo 2^32 ms (49.7 days)."),
        ],
    )
    return Database(messages=[pack, volts, temps, sync],
                    nodes=[Node("BMS", comment="Battery management system"),
                           Node("SOCD", comment="SOC estimator")])


# ---------------------------------------------------------------------------------------
# output: what the estimator publishes
# ---------------------------------------------------------------------------------------
SOC_FRAME_ID = 0x18FF50E5
PARAMS_FRAME_ID = 0x18FF51E5
SUMMARY_FRAME_ID = 0x18FF52E5
STATUS_FRAME_ID = 0x18FF53E5
PACK_USABLE_FRAME_ID = 0x18FF54E5
HEALTH_FRAME_ID = 0x18FF55E5  # 0x18FF54E5 is SOCD_PackUsable's


def output_database(max_cells: int = MAX_OUTPUT_CELLS) -> Database:
    ids = list(range(max_cells))
    soc = Message(
        frame_id=SOC_FRAME_ID, name="SOCD_CellSoc", length=8, cycle_time=1000, senders=["SOCD"],
        is_extended_frame=True, comment="Per-cell SOC and its standard deviation; one frame per cell.",
        signals=[
            _sig("SOCD_SocCellIndex", 0, 8, is_mux=True, minimum=0, maximum=max_cells - 1,
                 comment="Cell index, 0-based."),
            _sig("SOCD_Soc", 8, 16, scale=0.01, minimum=0, maximum=100, unit="%", mux_ids=ids,
                 mux_signal="SOCD_SocCellIndex", comment="State of charge."),
            _sig("SOCD_SocStd", 24, 16, scale=0.01, minimum=0, maximum=100, unit="%", mux_ids=ids,
                 mux_signal="SOCD_SocCellIndex", comment="Standard deviation of SOC (1 sigma)."),
            _sig("SOCD_SocStale", 40, 1, mux_ids=ids, mux_signal="SOCD_SocCellIndex",
                 comment="1 = this cell's inputs are stale; SOC is held, not extrapolated."),
            _sig("SOCD_SocCounter", 44, 4, comment="Rolling counter, +1 per frame, modulo 16."),
        ],
    )
    params = Message(
        frame_id=PARAMS_FRAME_ID, name="SOCD_CellParams", length=8, cycle_time=1000,
        senders=["SOCD"], is_extended_frame=True,
        comment="Per-cell identified MTS-FOM parameters (Zeng Fig. 1); one frame per cell.",
        signals=[
            _sig("SOCD_ParCellIndex", 0, 8, is_mux=True, minimum=0, maximum=max_cells - 1,
                 comment="Cell index, 0-based."),
            _sig("SOCD_ROhm", 8, 12, scale=0.1, unit="mOhm", mux_ids=ids, mux_signal="SOCD_ParCellIndex",
                 comment="Ohmic resistance R_ohm."),
            _sig("SOCD_RCt", 20, 12, scale=0.1, unit="mOhm", mux_ids=ids, mux_signal="SOCD_ParCellIndex",
                 comment="Charge-transfer resistance R_ct."),
            _sig("SOCD_RDf", 32, 12, scale=0.1, unit="mOhm", mux_ids=ids, mux_signal="SOCD_ParCellIndex",
                 comment="Diffusion resistance R_df."),
            _sig("SOCD_M", 44, 8, scale=0.004, minimum=0, maximum=1, mux_ids=ids,
                 mux_signal="SOCD_ParCellIndex", comment="Charge-transfer CPE order m."),
            _sig("SOCD_N", 52, 8, scale=0.004, minimum=0, maximum=1, mux_ids=ids,
                 mux_signal="SOCD_ParCellIndex", comment="Diffusion CPE order n."),
            _sig("SOCD_ParCounter", 60, 4, comment="Rolling counter, +1 per frame, modulo 16."),
        ],
    )
    summary = Message(
        frame_id=SUMMARY_FRAME_ID, name="SOCD_PackSummary", length=8, cycle_time=1000,
        senders=["SOCD"], is_extended_frame=True, comment="Pack SOC summary over fresh cells.",
        signals=[
            _sig("SOCD_SocMin", 0, 16, scale=0.01, minimum=0, maximum=100, unit="%"),
            _sig("SOCD_SocMean", 16, 16, scale=0.01, minimum=0, maximum=100, unit="%"),
            _sig("SOCD_SocMax", 32, 16, scale=0.01, minimum=0, maximum=100, unit="%"),
            _sig("SOCD_SocMinCell", 48, 8, comment="0-based index of the cell with the lowest SOC."),
            _sig("SOCD_SocMaxCell", 56, 8, comment="0-based index of the cell with the highest SOC."),
        ],
    )
    status_signals = [
        _sig(f"SOCD_Flag{camel(name)}", bit, 1, comment=f"Status word bit {bit}: {text}.")
        for bit, (name, text) in enumerate(STATUS_FLAGS)
    ]
    status_signals += [
        _sig("SOCD_FramesRejected", 32, 16, comment="Input frames rejected since start (saturates)."),
        _sig("SOCD_StaleCells", 48, 8, comment="Number of cells with stale inputs (saturates)."),
        _sig("SOCD_StatusCounter", 56, 4, comment="Rolling counter, +1 per frame, modulo 16."),
    ]
    status = Message(
        frame_id=STATUS_FRAME_ID, name="SOCD_Status", length=8, cycle_time=1000, senders=["SOCD"],
        is_extended_frame=True, signals=status_signals,
        comment="Estimator health: bits 0-31 are the status word (named flags, rest reserved).",
    )
    usable = Message(
        frame_id=PACK_USABLE_FRAME_ID, name="SOCD_PackUsable", length=8, cycle_time=1000,
        senders=["SOCD"], is_extended_frame=True,
        comment="Pack SOC as a BMS limits it: usable SOC, remaining energy, imbalance, weakest cell.",
        signals=[
            _sig("SOCD_UsableSoc", 0, 16, scale=0.01, minimum=0, maximum=100, unit="%",
                 comment="Usable SOC = D / (D + H), D = min_i SOC_i*C_i (charge the weakest cell can give), "
                         "H = min_i (1 - SOC_i)*C_i (charge the fullest cell can take)."),
            _sig("SOCD_RemainingEnergy", 16, 19, unit="Wh",
                 comment="Energy stored above each cell's empty point, sum_i C_i * integral of OCV_i over "
                         "[0, SOC_i] (saturates)."),
            _sig("SOCD_PackUsableValid", 35, 1,
                 comment="1 = the figures come from cell estimates; 0 = no estimate yet, or usable SOC "
                         "undefined (no cell can charge and none can discharge)."),
            _sig("SOCD_ImbalanceAh", 36, 16, scale=0.001, unit="Ah",
                 comment="max_i SOC_i*C_i - min_i SOC_i*C_i (saturates)."),
            _sig("SOCD_WeakestCell", 52, 8,
                 comment="0-based index of the cell with the least charge (it limits discharge)."),
            _sig("SOCD_PackUsableCounter", 60, 4, comment="Rolling counter, +1 per frame, modulo 16."),
        ],
    )
    health = Message(
        frame_id=HEALTH_FRAME_ID, name="SOCD_CellHealth", length=8, cycle_time=1000, senders=["SOCD"],
        is_extended_frame=True,
        comment="Per-cell state of health: estimated capacity and resistance growth; one frame per cell.",
        signals=[
            _sig("SOCD_HlthCellIndex", 0, 8, is_mux=True, minimum=0, maximum=max_cells - 1,
                 comment="Cell index, 0-based."),
            _sig("SOCD_CapacityPct", 8, 16, scale=0.01, unit="%", mux_ids=ids, mux_signal="SOCD_HlthCellIndex",
                 comment="Estimated capacity / the cell profile's capacity (SOH-energy)."),
            _sig("SOCD_CapacityStdPct", 24, 12, scale=0.01, unit="%", mux_ids=ids,
                 mux_signal="SOCD_HlthCellIndex", comment="Standard deviation of SOCD_CapacityPct (1 sigma)."),
            _sig("SOCD_ResistancePct", 36, 12, scale=0.1, unit="%", mux_ids=ids, mux_signal="SOCD_HlthCellIndex",
                 comment="(R_ohm + R_ct) / the profile's at the cell's temperature and SOC (SOH-power)."),
            _sig("SOCD_HlthCounter", 60, 4, comment="Rolling counter, +1 per frame, modulo 16."),
        ],
    )
    return Database(messages=[soc, params, summary, status, usable, health],
                    nodes=[Node("SOCD", comment="SOC estimator")])


# ---------------------------------------------------------------------------------------
# a user's own DBC, unlike ours in every way the mapping has to absorb
# ---------------------------------------------------------------------------------------
def user_example_database(n_cells: int = 12) -> Database:
    """ACME BMS: big-endian, current positive = discharge at 0.1 A, 3 cells a frame."""
    rx = ["ESTIMATOR"]
    n_blocks = math.ceil(n_cells / 3)
    msgs = [
        Message(frame_id=0x3A0, name="ACME_Power", length=6, cycle_time=20, senders=["ACME"],
                signals=[
                    _sig("ACME_Idc", 7, 16, signed=True, scale=0.1, order="big_endian", unit="A",
                         receivers=rx, comment="DC current, positive = discharge."),
                    _sig("ACME_Vdc", 23, 16, scale=0.02, order="big_endian", unit="V", receivers=rx),
                    _sig("ACME_Alive", 39, 8, order="big_endian", receivers=rx,
                         comment="Alive counter, +1 per frame, modulo 256."),
                ]),
    ]
    vs = [
        _sig("ACME_Alive2", 7, 8, order="big_endian", receivers=rx, comment="Alive counter mod 256."),
        _sig("ACME_Page", 15, 8, is_mux=True, minimum=0, maximum=n_blocks - 1, order="big_endian",
             receivers=rx),
    ]
    for cell in range(n_cells):
        block, slot = divmod(cell, 3)
        vs.append(_sig(f"ACME_U_{chr(ord('a') + slot)}{block}", 23 + 16 * slot, 16, scale=0.0001,
                       order="big_endian", unit="V", mux_ids=[block], mux_signal="ACME_Page",
                       receivers=rx, comment=f"Cell {cell} (0-based) voltage, 0.1 mV/bit."))
    msgs.append(Message(frame_id=0x3B0, name="ACME_CellBlock", length=8, cycle_time=50,
                        senders=["ACME"], signals=vs))
    ts = [_sig("ACME_TempAlive", 7, 8, order="big_endian", receivers=rx)]
    n_sensors = math.ceil(n_cells / 5)
    for s in range(n_sensors):
        ts.append(_sig(f"ACME_NTC{s}", 15 + 8 * s, 8, offset=-40, scale=1.0, order="big_endian",
                       unit="degC", receivers=rx, comment="NTC, 1 degC/bit, offset -40."))
    msgs.append(Message(frame_id=0x3C0, name="ACME_Thermal", length=1 + n_sensors, cycle_time=500,
                        senders=["ACME"], signals=ts))
    return Database(messages=msgs, nodes=[Node("ACME"), Node("ESTIMATOR")])


def _dump(db: Database, path: Path) -> None:
    text = db.as_dbc_string()
    # cantools orders SG_ lines arbitrarily in places; reload to prove the file is valid
    cantools.database.load_string(text, "dbc", strict=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(f"wrote {path} ({len(db.messages)} messages, "
          f"{sum(len(m.signals) for m in db.messages)} signals)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", type=int, default=96, help="series cells on the BMS bus (default 96)")
    ap.add_argument("--temps", type=int, default=24, help="temperature sensors (default 24)")
    ap.add_argument("--out-dir", type=Path, default=HERE, help="where to write (default: dbc/)")
    ap.add_argument("--user-example", type=Path, nargs="?", const=ROOT / "configs" / "user_dbc_example" /
                    "acme_bms.dbc", help="also write the user-DBC example (default path "
                    "configs/user_dbc_example/acme_bms.dbc)")
    args = ap.parse_args(argv)
    if not 1 <= args.cells <= MAX_OUTPUT_CELLS:
        ap.error(f"--cells must be 1..{MAX_OUTPUT_CELLS}")
    if not 1 <= args.temps <= 4 * 256:
        ap.error("--temps must be 1..1024")
    _dump(bms_database(args.cells, args.temps), args.out_dir / "bms_pack.dbc")
    _dump(output_database(), args.out_dir / "socd_output.dbc")
    if args.user_example:
        _dump(user_example_database(), args.user_example)
    return 0


if __name__ == "__main__":
    sys.exit(main())
