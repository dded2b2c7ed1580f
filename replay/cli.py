"""``socd replay``: play a recording or a CAN log onto a bus, in real time or faster.

    socd replay recording.csv                        # a cell recording -> 96-cell pack, virtual bus
    socd replay -i socketcan -c vcan0 drive.csv --speed 10 --spread-soc 0.02 --seed 1
    socd replay capture.blf --loop --drop 0.01 --jitter 0.002
    socd replay capture.log.gz                       # gzip-compressed logs play too
    socd replay drive.csv --fast --record pack.mf4   # only write a python-can log

A cell recording (CSV ``time_s,current_a,voltage_v,temperature_c``) is expanded to a pack
and encoded with the config's input DBC and mapping; anything else is read with python-can's
``LogReader`` (asc, blf, csv, log, mf4, trc, and each of them ``.gz``-compressed) and played
frame by frame.  The bus is chosen as for ``socd run`` (flags > ``--config``'s ``[bus]`` >
python-can's ``CAN_INTERFACE``/``~/.canrc`` > the bundled default); sending to python-can's
in-process ``virtual`` bus draws a warning, since no other process can hear it.
"""

from __future__ import annotations

import argparse
import csv
import sys
import threading
from collections import Counter
from pathlib import Path

import can

from replay.faults import FaultSpec
from replay.pack import SpreadSpec, first_outside_unit, known_start, pack_frames
from replay.player import LOG_SUFFIXES, log_format, play, read_log
from service.bus.cli_args import BusConfigError, add_bus_arguments, bus_flags_given, resolve_bus
from service.bus.decoder import frame_key, message_key
from service.commands.common_args import (
    SEED,
    add_cell_argument,
    add_common_arguments,
    add_soc0_argument,
    bus_gap,
    float_in,
    non_negative_float,
    output_file,
    plain_text,
    positive_int,
    probability,
    progress_enabled,
    recording_file,
    recording_help,
    recording_path_problem,
    refuse_overwriting_inputs,
    refuse_shared_outputs,
    relative_sigma,
    replay_speed,
    sensor_temperature_sigma,
    setup_logging,
    start_soc_sigma,
    stuck_cell,
)
from service.errors import MissingExtra, UserError
from service.extras import install_hint, installed


def add_subparser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "replay",
        help="play a recording or CAN log onto a bus (real time or faster, with faults)",
        description=plain_text(__doc__.split("\n\n")[0]),
        epilog="Cell recordings are expanded to a pack; python-can logs are played as they are.",
    )
    p.add_argument("input", type=recording_file, help=recording_help(
        "cell recording CSV, or a python-can log (" + ", ".join(LOG_SUFFIXES) + ", optionally .gz)"))
    p.add_argument("--config", help="socd's config TOML (as for socd run) for the DBC, mapping and pack size "
                   "(default: the packaged default.toml); its [bus] fills bus flags not given")
    add_bus_arguments(p)

    g = p.add_argument_group("pack (cell recordings only)")
    g.add_argument("--cells", type=positive_int, help="cells in the pack (default: the config's pack.n_cells)")
    add_cell_argument(g, old_profile_alias=True,
                      help="cell profile for the OCV table (default: the config's cell_profile)")
    add_soc0_argument(g, old_start_soc_alias=True,
                      help="SOC at the first sample, 0..1 (default: 1 for the bundled drive, which starts "
                           "fully charged; else from the first rest voltage)")
    g.add_argument("--spread-capacity", type=relative_sigma, default=0.0, metavar="REL",
                   help="σ of the cells' capacity, relative, clipped at ±3σ (default 0: every cell the profile's; socd demo uses 0.02)")
    g.add_argument("--spread-resistance", type=relative_sigma, default=0.0, metavar="REL",
                   help="σ of the cells' R_ohm, relative, clipped at ±3σ (default 0; socd demo uses 0.05)")
    g.add_argument("--spread-soc", type=start_soc_sigma, default=0.0, metavar="SOC",
                   help="σ of start SOC (absolute, 0-0.2; draws are clipped at ±3σ; default 0)")
    g.add_argument("--spread-temperature", type=sensor_temperature_sigma, default=0.0, metavar="DEGC",
                   help="σ of per-sensor temperature offset, K (0-10; draws are clipped at ±3σ; default 0)")
    g.add_argument("--seed", type=SEED, default=0, help="seed of the spread and the faults (default 0)")
    g.add_argument("--time-offset", type=float_in(-1e10, 1e10, "an offset in s"), default=0.0, metavar="S",
                   help="add to frame timestamps (|S| up to 1e10: Unix times fit)")
    g.add_argument("--truth-out", metavar="FILE.csv", type=output_file(), help="write per-cell truth SOC")

    g = p.add_argument_group("pacing")
    g.add_argument("--speed", type=replay_speed, default=None, help="1 = real time (default), 10 = ten times "
                   "faster, 0 = as fast as possible")
    g.add_argument("--fast", action="store_true", help="same as --speed 0")
    g.add_argument("--loop", nargs="?", const=True, default=False, type=positive_int, metavar="N",
                   help="repeat (forever, or N passes); timestamps keep increasing")
    g.add_argument("--start", type=non_negative_float, metavar="S", help="skip the first S seconds")
    g.add_argument("--stop", type=non_negative_float, metavar="S", help="stop at S seconds (from the first frame)")

    g = p.add_argument_group("faults (seeded by --seed)")
    g.add_argument("--drop", type=probability, default=0.0, metavar="P", help="drop each frame with probability P")
    g.add_argument("--duplicate", type=probability, default=0.0, metavar="P", help="send a frame twice")
    g.add_argument("--reorder", type=probability, default=0.0, metavar="P", help="swap a frame with the next")
    g.add_argument("--jitter", type=float_in(0.0, 10.0, "a delay in s"), default=0.0, metavar="SECONDS",
                   help="delay frames by U(0, S), S up to 10")
    g.add_argument("--corrupt", type=probability, default=0.0, metavar="P", help="flip a payload bit or change DLC")
    g.add_argument("--stuck-cell", action="append", default=[], type=stuck_cell, metavar="I[:T0]",
                   help="freeze cell I's (0-based) voltage from T0 s (repeatable)")
    g.add_argument("--bus-gap", action="append", default=[], type=bus_gap, metavar="T0:DURATION",
                   help="no frames from T0 for DURATION s (repeatable)")

    g = p.add_argument_group("output")
    g.add_argument("--record", metavar="OUT", type=record_file, help="write the frames to a python-can log "
                   "(" + ", ".join(LOG_SUFFIXES) + ", optionally .gz), which socd replay reads back; with no bus "
                   "flags only the log is written")
    g.add_argument("--no-send", action="store_true", help="do not open a bus")
    add_common_arguments(p, progress=True, old_no_progress_alias=True, bounds=True)
    p.set_defaults(func=run)
    return p


def is_cell_recording(path: Path) -> bool:
    """A CSV whose header names the recording columns (python-can CSV logs start otherwise).

    Looks at the first line only and never raises: a file that cannot be read or decoded is
    "not a recording" here, and the log validation names what is wrong with it.
    """
    if path.suffix.lower() != ".csv":
        return False
    try:
        with path.open("rb") as fh:
            first = fh.readline(65536).decode("utf-8-sig", errors="replace")
    except OSError:
        return False
    try:
        header = next(csv.reader(first.splitlines()[:1]), [])
    except csv.Error:
        return False
    return {"time_s", "current_a", "voltage_v"} <= {h.strip() for h in header}


def _config(args):
    from service.config import DEFAULT_CONFIG, ConfigError, check_input_mapping, load_config

    try:
        config = load_config(args.config, check_files=False) if args.config else load_config(check_files=False)
        # the input DBC and the mapped signals are what a replay encodes with: check them up front
        check_input_mapping(config, str(args.config or DEFAULT_CONFIG))
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    return config


def truth_leaves_cell(pack) -> str | None:
    """Where the first cell's true SOC leaves [0, 1] (beyond a rounding), or None."""
    if (first := first_outside_unit(pack.truth_soc, margin=1e-3)) is None:
        return None
    k, cell = first
    reach = float(pack.truth_soc[:, cell].min() if pack.truth_soc[k, cell] < 0 else pack.truth_soc[:, cell].max())
    return (f"cell {cell}'s true SOC leaves [0, 1] {pack.time_s[k] - pack.time_s[0]:.0f} s into the recording "
            f"and reaches {reach:.3f}")


def run(args: argparse.Namespace) -> int:
    setup_logging(args)
    from service.config import DEFAULT_CONFIG
    from service.validation import InputFileError, check_can_log

    path = Path(args.input)
    if path.is_dir():
        raise UserError(f"{path}: is a folder, not a recording or CAN log")
    if (why := recording_path_problem(path, "no such file")) is not None:
        raise UserError(f"{path}: {why}")
    refuse_shared_outputs([("--record", args.record), ("--truth-out", args.truth_out)])
    mf4_files = [f for f in (str(path), args.record) if f and f.lower().endswith(".mf4")]
    if mf4_files and not installed("asammdf"):
        raise MissingExtra(f"{mf4_files[0]}: MF4 {install_hint('asammdf')}")
    config = _config(args)
    # every file the replay reads, the config's own included, is an input an output must not replace
    inputs = [path, getattr(args, "cell", None), args.config or DEFAULT_CONFIG, config.cell_profile,
              config.dbc.input, config.dbc.output]
    for flag, out in (("--record", args.record), ("--truth-out", args.truth_out)):
        refuse_overwriting_inputs(out, inputs, flag)
    if args.stop is not None and args.stop <= 0:
        raise UserError(f"--stop {args.stop:g} plays no frame (it counts seconds from the first frame); give a later time")
    if args.stop is not None and args.start is not None and args.stop <= args.start:
        raise UserError(f"--stop ({args.stop:g} s) must be after --start ({args.start:g} s)")
    try:
        faults = FaultSpec(
            drop=args.drop, duplicate=args.duplicate, reorder=args.reorder, jitter_s=args.jitter,
            corrupt=args.corrupt, stuck_cells=list(args.stuck_cell), bus_gaps=list(args.bus_gap), seed=args.seed,
        )
    except ValueError as exc:
        raise UserError(str(exc)) from None

    total = None
    pack = None
    if is_cell_recording(path):
        from service.cell.profile import ProfileError, load_profile
        from service.cell.truth import check_current_sign
        from service.recording import load_recording

        recording = load_recording(path)
        check_current_sign(recording)  # a charge-positive log would replay every cell the wrong way
        length_s = float(recording.time_s[-1] - recording.time_s[0])
        if args.start is not None and args.start >= length_s:
            raise UserError(f"--start {args.start:g} s is past the end of {path} ({length_s:g} s long)")
        profile_path = Path(args.cell) if args.cell else config.cell_profile
        try:
            profile = load_profile(profile_path)
        except ProfileError as exc:
            # a --cell given names itself; the config's profile is worth pointing past
            raise UserError(str(exc) if args.cell else f"{exc} (the config's cell_profile; give --cell for "
                            "another)") from None
        spread = SpreadSpec(args.spread_capacity, args.spread_resistance, args.spread_soc, args.spread_temperature)
        try:
            start = args.soc0 if args.soc0 is not None else known_start(path)
            frames, pack = pack_frames(recording, config, profile, args.cells, spread, args.seed,
                                       start_soc=start, time_offset_s=args.time_offset, lazy=True)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        if (leaves := truth_leaves_cell(pack)) is not None:
            print(f"socd replay: warning: {leaves}; the voltages sent beyond it are the OCV table's extrapolation "
                  "(give a --soc0 further from that end, or a shorter --stop)", file=sys.stderr)
        if args.cells:
            # the fault injector reads the config's whole mapping; the pack replayed is narrower
            for cell, _ in args.stuck_cell:
                if cell >= args.cells:
                    raise UserError(f"--stuck-cell {cell}: the replayed pack has {args.cells} cells (--cells), "
                                    f"0..{args.cells - 1}")
        per_sample = sum(1 for _ in _one_sample(config, args.cells))
        # a --start/--stop window plays an unknown share of the frames: no total, no ETA
        total = per_sample * len(pack) if args.start is None and args.stop is None else None
        if args.truth_out:
            pack.write_truth_csv(args.truth_out)
            if (caution := pack.start.caution()) is not None:
                print(f"socd replay: warning: {args.truth_out}: {caution}", file=sys.stderr)
    else:
        if log_format(path) is None:
            raise UserError(f"{path}: not a cell recording and not a python-can log "
                            f"({', '.join(LOG_SUFFIXES)}, optionally .gz)")
        ids: Counter[tuple[int, bool]] = Counter()

        def counted(p: Path):
            for msg in read_log(p):
                ids[frame_key(msg)] += 1
                yield msg

        try:  # read it to the end once, so a bad log fails here and not halfway through a replay
            total = check_can_log(path, LOG_SUFFIXES, counted)
        except InputFileError as exc:
            raise UserError(str(exc)) from None
        warn_unknown_ids(path, ids, config)
        warn_cut_log(path, total)
        if args.time_offset:
            frames = _offset(read_log(path), args.time_offset)
        else:
            frames = read_log(path)

    send = not args.no_send and (bus_flags_given(args) or not args.record)
    speed = 0.0 if args.fast else args.speed
    if speed is None:
        speed = 1.0 if send else 0.0

    listeners = []
    logger = None
    if args.record:
        try:
            logger = can.Logger(args.record)
        except Exception as exc:  # noqa: BLE001 - unknown suffix, unwritable path
            raise UserError(f"--record {args.record}: {exc}") from None
        listeners.append(logger)
    bus = None
    try:
        if send:
            try:
                resolved = resolve_bus(args, config, user_config=args.config is not None)
            except BusConfigError as exc:
                raise UserError(str(exc)) from None
            if resolved.bus.interface == "virtual":
                print(f"socd replay: warning: sending to python-can's in-process 'virtual' bus "
                      f"{resolved.describe()}: no other process can hear it; give -i/-c (e.g. -i socketcan "
                      f"-c vcan0) or set CAN_INTERFACE/CAN_CHANNEL", file=sys.stderr)
            try:
                bus = can.Bus(**resolved.kwargs())
            except Exception as exc:  # noqa: BLE001 - every backend raises its own kinds
                raise UserError(f"cannot open bus {resolved.describe()}: {exc}") from None
        stop_event = threading.Event()
        try:
            stats = play(bus, frames, speed=speed, faults=faults if faults.active else None, stop_event=stop_event,
                         progress=progress_enabled(args), start=args.start,
                         stop=args.stop, loop=args.loop, listeners=listeners, total=total, config=config)
        except KeyboardInterrupt:
            stop_event.set()
            return 130
        except (ValueError, OverflowError, TypeError) as exc:  # a frame the DBC cannot encode, say
            failed = exc
        else:
            failed = None
    finally:
        if bus is not None:
            bus.shutdown()
        if logger is not None:
            logger.stop()
    if failed is not None:
        if args.record:
            Path(args.record).unlink(missing_ok=True)  # nothing written on failure
        why = str(failed).splitlines()[0] if str(failed) else type(failed).__name__
        raise UserError(f"{path}: replay stopped: {why} (input DBC {config.dbc.input})")
    if pack is not None and pack.clipped:
        what = ", ".join(f"{name} {n}x" for name, n in pack.clipped.most_common())
        print(f"socd replay: warning: values beyond their signal's minimum/maximum in {config.dbc.input} were "
              f"sent clipped to it: {what}", file=sys.stderr)
    lost = [] if pack is None else [f"{name} {pack.zeroed[name]} of {n}" for name, n in pack.nonzero.items()
                                    if pack.zeroed[name] > n / 2]
    if lost:
        print(f"socd replay: warning: most values of a signal in {config.dbc.input} are smaller than half its step "
              f"and were sent as its offset (a scale in the mapping, e.g. mapping.current_scale, too large?): "
              f"{', '.join(lost)}", file=sys.stderr)
    verb = "sent" if send else ("recorded to " + str(args.record) if args.record else "built (--no-send: no bus, no --record)")
    print(f"socd replay: {stats.frames_sent} frames {verb}, {stats.frames_failed} failed, "
          f"{stats.span_s:.1f} s of recording in {stats.duration_s:.1f} s"
          + (f", faults {stats.faults}" if stats.faults else ""), file=sys.stderr)
    return 0 if stats.frames_failed == 0 else 1


def record_file(text: str) -> str:
    """``--record``: a log python-can writes and :func:`read_log` reads back (python-can also writes
    ``.txt`` and others that no reader opens again)."""
    if log_format(text) is None:
        raise argparse.ArgumentTypeError(f"{text}: expected a python-can log ({', '.join(LOG_SUFFIXES)}, "
                                         "optionally .gz) that socd replay can read back")
    return output_file()(text)


def _one_sample(config, n_cells):
    from replay.pack import FrameBuilder, narrow_config

    cfg = config if not n_cells or n_cells == config.pack.n_cells else narrow_config(config, n_cells)
    return FrameBuilder(cfg).sample_templates


def unknown_ids(ids: Counter[tuple[int, bool]], config) -> Counter[tuple[int, bool]]:
    """The frame counts of ``ids`` (``(arbitration id, extended)`` -> frames) that the config's
    input DBC does not define: a daemon on that config rejects each of them."""
    known = {message_key(m) for m in config.input_db().messages}
    return Counter({key: n for key, n in ids.items() if key not in known})


def warn_unknown_ids(path: Path, ids: Counter[tuple[int, bool]], config) -> None:
    """Say, before sending, how many of a log's frames the input DBC does not know."""
    unknown = unknown_ids(ids, config)
    if not unknown:
        return
    # an extended ID in eight hex digits, a standard one in three, as candump writes them
    shown = ", ".join(f"0x{i:08X} {n}x" if ext else f"0x{i:03X} {n}x" for (i, ext), n in unknown.most_common(5))
    more = f" and {len(unknown) - 5} more IDs" if len(unknown) > 5 else ""
    print(f"socd replay: warning: {sum(unknown.values())} of {sum(ids.values())} frames in {path} carry IDs the "
          f"input DBC {config.dbc.input} does not define ({shown}{more}): they are sent as logged, and a socd "
          f"daemon on this config counts them as rejected", file=sys.stderr)


#: the line an ASC log's writer (python-can, Vector tools) closes the file with
ASC_END = "End TriggerBlock"


def log_cut_short(path: Path) -> str | None:
    """Why a plain ASC or BLF log looks cut short, or None: an ASC log without :data:`ASC_END` (its
    writer did not close it), a BLF log smaller than the size its header states (a copy cut off)."""
    suffix = path.suffix.lower()
    if suffix == ".asc":
        with path.open("rb") as fh:
            fh.seek(max(0, path.stat().st_size - 4096))
            tail = fh.read().decode("utf-8", errors="replace").strip()
        last = tail.splitlines()[-1].strip() if tail else ""
        return None if last.startswith(ASC_END) else f"it does not end with '{ASC_END}'"
    if suffix == ".blf":
        import can

        with can.BLFReader(str(path)) as reader:
            stated = int(reader.file_size)
        size = path.stat().st_size
        return f"it holds {size} of the {stated} bytes its header states" if 0 < size < stated else None
    return None


def warn_cut_log(path: Path, frames: int) -> None:
    """Say when a log looks cut short (:func:`log_cut_short`): the replay plays the frames up to the cut."""
    why = log_cut_short(path)
    if why is not None:
        print(f"socd replay: warning: {path}: {why}, so the log may have been cut short; the {frames} frames "
              "read up to its end are replayed", file=sys.stderr)


def _offset(frames, offset):
    for m in frames:
        m.timestamp += offset
        yield m
