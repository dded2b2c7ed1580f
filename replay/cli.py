"""``socd replay``: play a recording or a CAN log onto a bus, in real time or faster.

    socd replay recording.csv                        # a cell recording -> 96-cell pack, virtual bus
    socd replay -i socketcan -c vcan0 drive.csv --speed 10 --spread-soc 0.02 --seed 1
    socd replay capture.blf --loop --drop 0.01 --jitter 0.002
    socd replay drive.csv --fast --record pack.mf4   # only write a python-can log

A cell recording (CSV ``time_s,current_a,voltage_v,temperature_c``) is expanded to a pack
and encoded with the config's input DBC and mapping; anything else is read with python-can's
``LogReader`` (asc, blf, csv, log, mf4, trc) and played frame by frame.
"""

from __future__ import annotations

import argparse
import csv
import sys
import threading
from pathlib import Path

from replay.faults import FaultSpec, parse_gap, parse_stuck
from replay.pack import SpreadSpec, pack_frames
from replay.player import LOG_SUFFIXES, play, read_log
from service.bus.cli_args import add_bus_arguments, create_bus_from_namespace
from service.errors import UserError


def add_subparser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "replay",
        help="play a recording or CAN log onto a bus (real time or faster, with faults)",
        description=__doc__.split("\n\n")[0],
        epilog="Cell recordings are expanded to a pack; python-can logs are played as they are.",
    )
    p.add_argument("input", help="cell recording CSV, or a python-can log (" + ", ".join(LOG_SUFFIXES) + ")")
    p.add_argument("--config", help="SocdConfig TOML for the DBC, mapping and pack size "
                   "(default: configs/default.toml); its [bus] fills bus flags not given")
    add_bus_arguments(p)

    g = p.add_argument_group("pack (cell recordings only)")
    g.add_argument("--cells", type=int, help="cells in the pack (default: the config's pack.n_cells)")
    g.add_argument("--profile", help="cell profile for the OCV table (default: the config's cell_profile)")
    g.add_argument("--start-soc", type=float, help="SOC at the first sample, 0..1 (default: from the "
                   "first rest voltage)")
    g.add_argument("--spread-capacity", type=float, default=0.0, metavar="REL", help="σ of capacity (relative)")
    g.add_argument("--spread-resistance", type=float, default=0.0, metavar="REL", help="σ of R_ohm (relative)")
    g.add_argument("--spread-soc", type=float, default=0.0, metavar="SOC", help="σ of start SOC (absolute)")
    g.add_argument("--spread-temperature", type=float, default=0.0, metavar="DEGC",
                   help="σ of per-sensor temperature offset")
    g.add_argument("--seed", type=int, default=0, help="seed of the spread and the faults (default 0)")
    g.add_argument("--time-offset", type=float, default=0.0, metavar="S", help="add to frame timestamps")
    g.add_argument("--truth-out", metavar="FILE.csv", help="write per-cell truth SOC")

    g = p.add_argument_group("pacing")
    g.add_argument("--speed", type=float, default=None, help="1 = real time (default), 10 = ten times "
                   "faster, 0 = as fast as possible")
    g.add_argument("--fast", action="store_true", help="same as --speed 0")
    g.add_argument("--loop", nargs="?", const=True, default=False, type=int, metavar="N",
                   help="repeat (forever, or N passes); timestamps keep increasing")
    g.add_argument("--start", type=float, metavar="S", help="skip the first S seconds")
    g.add_argument("--stop", type=float, metavar="S", help="stop at S seconds (from the first frame)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")

    g = p.add_argument_group("faults (seeded by --seed)")
    g.add_argument("--drop", type=float, default=0.0, metavar="P", help="drop each frame with probability P")
    g.add_argument("--duplicate", type=float, default=0.0, metavar="P", help="send a frame twice")
    g.add_argument("--reorder", type=float, default=0.0, metavar="P", help="swap a frame with the next")
    g.add_argument("--jitter", type=float, default=0.0, metavar="SECONDS", help="delay frames by U(0, S)")
    g.add_argument("--corrupt", type=float, default=0.0, metavar="P", help="flip a payload bit or change DLC")
    g.add_argument("--stuck-cell", action="append", default=[], metavar="I[:T0]",
                   help="freeze cell I's voltage from T0 s (repeatable)")
    g.add_argument("--bus-gap", action="append", default=[], metavar="T0:DURATION",
                   help="no frames from T0 for DURATION s (repeatable)")

    g = p.add_argument_group("output")
    g.add_argument("--record", metavar="OUT", help="write the frames to a python-can log "
                   "(" + ", ".join(LOG_SUFFIXES) + "); with no bus flags only the log is written")
    g.add_argument("--no-send", action="store_true", help="do not open a bus")
    p.set_defaults(func=run)
    return p


def is_cell_recording(path: Path) -> bool:
    """A CSV whose header names the recording columns (python-can CSV logs start otherwise)."""
    if path.suffix.lower() != ".csv":
        return False
    try:
        with path.open(newline="") as fh:
            header = next(csv.reader(fh), [])
    except OSError:
        return False
    return {"time_s", "current_a", "voltage_v"} <= {h.strip() for h in header}


def _config(args):
    from service.config import ConfigError, load_config

    try:
        return load_config(args.config, check_files=False) if args.config else load_config(check_files=False)
    except ConfigError as exc:
        raise UserError(str(exc)) from None


def run(args: argparse.Namespace) -> int:
    path = Path(args.input)
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    config = _config(args)
    try:
        faults = FaultSpec(
            drop=args.drop, duplicate=args.duplicate, reorder=args.reorder, jitter_s=args.jitter,
            corrupt=args.corrupt, stuck_cells=[parse_stuck(s) for s in args.stuck_cell],
            bus_gaps=[parse_gap(s) for s in args.bus_gap], seed=args.seed,
        )
    except ValueError as exc:
        raise UserError(str(exc)) from None

    total = None
    if is_cell_recording(path):
        from service.cell.profile import ProfileError, load_profile
        from service.recording import load_recording

        recording = load_recording(path)
        profile_path = Path(args.profile) if args.profile else config.cell_profile
        try:
            profile = load_profile(profile_path)
        except ProfileError as exc:
            raise UserError(f"{exc} (give --profile or set cell_profile in the config)") from None
        spread = SpreadSpec(args.spread_capacity, args.spread_resistance, args.spread_soc, args.spread_temperature)
        try:
            frames, pack = pack_frames(recording, config, profile, args.cells, spread, args.seed,
                                       start_soc=args.start_soc, time_offset_s=args.time_offset, lazy=True)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        per_sample = sum(1 for _ in _one_sample(config, args.cells))
        total = per_sample * len(pack)
        if args.truth_out:
            pack.write_truth_csv(args.truth_out)
    else:
        if path.suffix.lower() not in LOG_SUFFIXES:
            raise UserError(f"{path}: not a cell recording and not a python-can log ({', '.join(LOG_SUFFIXES)})")
        if args.time_offset:
            frames = _offset(read_log(path), args.time_offset)
        else:
            frames = read_log(path)

    bus_flags_given = any(k in args for k in ("interface", "channel"))
    send = not args.no_send and (bus_flags_given or not args.record)
    speed = 0.0 if args.fast else args.speed
    if speed is None:
        speed = 1.0 if send else 0.0

    listeners = []
    logger = None
    if args.record:
        import can

        try:
            logger = can.Logger(args.record)
        except Exception as exc:  # noqa: BLE001 - unknown suffix, unwritable path
            raise UserError(f"--record {args.record}: {exc}") from None
        listeners.append(logger)
    bus = None
    try:
        if send:
            try:
                bus = create_bus_from_namespace(args, config)
            except Exception as exc:  # noqa: BLE001
                raise UserError(f"cannot open bus: {exc}") from None
        stop_event = threading.Event()
        try:
            stats = play(bus, frames, speed=speed, faults=faults if faults.active else None, stop_event=stop_event,
                         progress=not args.no_progress and sys.stderr.isatty() or False, start=args.start,
                         stop=args.stop, loop=args.loop, listeners=listeners, total=total, config=config)
        except KeyboardInterrupt:
            stop_event.set()
            return 130
    finally:
        if bus is not None:
            bus.shutdown()
        if logger is not None:
            logger.stop()
    print(f"socd replay: {stats.frames_sent} frames sent, {stats.frames_failed} failed, "
          f"{stats.span_s:.1f} s of recording in {stats.duration_s:.1f} s"
          + (f", faults {stats.faults}" if stats.faults else ""), file=sys.stderr)
    return 0 if stats.frames_failed == 0 else 1


def _one_sample(config, n_cells):
    from replay.pack import FrameBuilder, narrow_config

    cfg = config if not n_cells or n_cells == config.pack.n_cells else narrow_config(config, n_cells)
    b = FrameBuilder(cfg)
    return b.templates + b.current_templates


def _offset(frames, offset):
    for m in frames:
        m.timestamp += offset
        yield m
