"""``socd demo``: replay → estimator → CAN + Zenoh in one process, no hardware (see :mod:`service.demo`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli import UserError
from service.commands.common_args import (
    SEED,
    add_cell_argument,
    add_common_arguments,
    add_soc0_argument,
    int_range,
    plot_file,
    positive_float,
    recording_file,
    recording_help,
    recording_path_problem,
    refuse_overwriting_inputs,
    refuse_shared_outputs,
    relative_sigma,
    replay_speed,
    setup_logging,
    text_stream,
    write_json,
)
from service.errors import MissingExtra

MAX_DEMO_CELLS = 256  # the output DBC's cell index is 8 bits; above 96 an input DBC is generated
DEFAULT_PLOT = Path("socd-demo.png")


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="the whole chain in one process on a virtual CAN bus and loopback Zenoh",
        description=(
            "Replay the bundled real drive cycle for a pack with a seeded per-cell spread onto a "
            "python-can virtual bus, estimate it with the service, publish on CAN and Zenoh "
            "(tcp/127.0.0.1, no multicast), and score every cell's SOC against the replay's truth."
        ),
    )
    parser.add_argument("--cells", type=int_range(1, MAX_DEMO_CELLS), default=8, help=f"cells in the pack, 1-{MAX_DEMO_CELLS} (default 8)")
    parser.add_argument("--speed", type=replay_speed, default=0.0,
                        help="replay speed: 1 = real time, 0 = as fast as possible (default 0)")
    parser.add_argument("--seconds", type=positive_float, default=None, metavar="S",
                        help="replay only the first S seconds of the recording")
    parser.add_argument("--recording", type=lambda t: Path(recording_file(t)), default=None,
                        help=recording_help("a recording CSV instead of the bundled one"))
    add_soc0_argument(parser, old_start_soc_alias=True,
                      help="true SOC at the recording's first sample, 0-1 (default: 1.0 for the bundled "
                           "drive, which starts fully charged; else the recording's soc_true, else read from "
                           "the first rest voltage; the summary says which, and when that voltage was still "
                           "relaxing)")
    add_cell_argument(parser, help="cell profile the service estimates with and the pack is built from "
                      "(default: the bundled Panasonic 18650PF profile)")
    parser.add_argument("--seed", type=SEED, default=0, help="seed of the per-cell spread (default 0)")
    parser.add_argument("--spread-capacity", type=relative_sigma, default=0.02, metavar="SIGMA",
                        help="σ of the cells' relative capacity, clipped at 3σ (default 0.02 = 2 %%)")
    parser.add_argument("--freeze-capacity", action="store_true",
                        help="estimate with the profile's capacity (estimator.capacity_estimation = 'off')")
    plots = parser.add_mutually_exclusive_group()
    plots.add_argument("--plot", type=plot_file, default=None, metavar="FILE",
                       help=f"PNG of SOC vs truth (default {DEFAULT_PLOT} in the working folder where matplotlib, "
                            "of the 'fit' extra, is installed)")
    plots.add_argument("--no-plot", action="store_true", help="write no plot")
    add_common_arguments(parser, json_out="the figures")
    parser.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    from service.assets import bundled_recording
    from service.cell.profile import ProfileError
    from service.config import DEFAULT_CELL_PROFILE
    from service.demo import run_demo, summary_text, write_plot
    from service.extras import install_hint, installed

    setup_logging(args)
    if not 1 <= args.cells <= MAX_DEMO_CELLS:
        raise UserError(f"--cells must be 1..{MAX_DEMO_CELLS}, got {args.cells}")
    if args.speed < 0:
        raise UserError(f"--speed must be >= 0, got {args.speed}")
    if args.seconds is not None and args.seconds <= 0:
        raise UserError(f"--seconds must be > 0, got {args.seconds}")
    if args.recording is not None and (why := recording_path_problem(args.recording, "no such recording")):
        raise UserError(f"{args.recording}: {why}")
    inputs = [args.recording or bundled_recording(), args.cell or DEFAULT_CELL_PROFILE]
    for flag, out in (("--json", args.json), ("--plot", args.plot)):
        refuse_overwriting_inputs(out, inputs, flag)
    refuse_shared_outputs([("--json", args.json), ("--plot", args.plot)])
    plot = args.plot
    if not installed("matplotlib"):
        if plot is not None:
            raise MissingExtra(f"--plot {install_hint('matplotlib')}")
    elif plot is None and not args.no_plot:
        plot = DEFAULT_PLOT
    try:
        result, traces = run_demo(args.cells, args.speed, args.seconds, recording_path=args.recording,
                                  start_soc=args.soc0, profile_path=args.cell, seed=args.seed,
                                  capacity_spread=args.spread_capacity,
                                  capacity_estimation="off" if args.freeze_capacity else None)
    except (FileNotFoundError, ProfileError) as exc:
        raise UserError(str(exc)) from None
    if result.steps == 0:
        # every sample was refused on the way in: a result of NaNs is no demo; say why, write nothing
        why = ", ".join(f"{k} {v}" for k, v in result.counters.items()
                        if v and any(w in k for w in ("range", "error", "reject", "stale", "waiting"))) or "no counter says why"
        raise UserError(f"{result.recording}: no sample was estimated ({result.frames_in} frames in; {why}); "
                        "its values may lie at the edge of what the service reads from the bus "
                        "(mapping.voltage_range_v, mapping.temperature_range_c)")
    out = text_stream(args)
    print(summary_text(result), file=out)
    if plot is not None:
        print(f"plot: {write_plot(plot, traces, result)}", file=out)
    elif not args.no_plot:
        print(f"plot: not written ({install_hint('matplotlib')})", file=out)
    write_json(args.json, result.to_json())
    return 0

