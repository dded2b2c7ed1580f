"""``socd run [--config FILE] [-i IFACE -c CHANNEL ...]``: the estimator service (see :mod:`service.daemon.daemon`).

The bus is python-can's flags, else the config's ``[bus]``, else python-can's own
configuration (``CAN_INTERFACE``/``CAN_CHANNEL``, ``~/.canrc``), else the bundled default
(see :mod:`service.bus.cli_args`).  Exit status: 0 after SIGTERM/SIGINT, 1 when the bus
failed to open ``bus.max_open_retries + 1`` times at start-up, 2 for a bad config.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path
from typing import Any

from service.bus.cli_args import add_bus_arguments
from service.cli import UserError
from service.commands.common_args import add_common_arguments, non_negative_int, setup_logging

log = logging.getLogger("service.run")


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run the estimator service on a CAN bus",
        description=(
            "Read the BMS bus, estimate each cell's SOC and parameters, publish them on CAN "
            "and Zenoh; checkpoint the estimator state and restore it on start. "
            "SIGTERM/SIGINT write a final checkpoint and exit cleanly."
        ),
        epilog="Bus: -i/-c flags > the config's [bus] > python-can's CAN_INTERFACE/CAN_CHANNEL or "
               "~/.canrc > the bundled default (virtual). Exit 1: the bus would not open.",
    )
    parser.add_argument("--config", type=Path, metavar="FILE",
                        help="socd TOML config (default: the bundled configs/default.toml)")
    add_bus_arguments(parser)
    parser.add_argument("--max-bus-retries", type=non_negative_int, default=None, metavar="N",
                        help="give up (exit 1) when the bus has failed to open N + 1 times at start-up; 0 = retry "
                             "for ever (default: the config's bus.max_open_retries). A bus that opened once is "
                             "reopened for as long as it takes")
    add_common_arguments(parser, log_level="info")
    parser.set_defaults(func=_run)


def load_run_config(args: argparse.Namespace):
    """The config with the bus resolved from flags, config and python-can (raises UserError)."""
    from service.bus.cli_args import BusConfigError, resolve_bus
    from service.config import ConfigError, load_config

    try:
        config = load_config(args.config)
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    try:
        resolved = resolve_bus(args, config, user_config=args.config is not None)
    except BusConfigError as exc:
        raise UserError(str(exc)) from None
    bus = resolved.bus
    if args.max_bus_retries is not None:
        bus = bus.model_copy(update={"max_open_retries": args.max_bus_retries})
    config.bus = bus
    return config, resolved


def _run(args: argparse.Namespace) -> int:
    from service.cell.profile import ProfileError
    from service.daemon.bus_open import BusUnavailable
    from service.daemon.daemon import Daemon
    from service.daemon.metrics import MetricsError
    from service.daemon.zenoh_pub import ZenohConfigError, config_from_section

    setup_logging(args)
    config, resolved = load_run_config(args)
    if config.output.zenoh_enabled:
        try:
            config_from_section(config.zenoh)  # a bad zenoh.config_file is a config error now, not a retry loop
        except ZenohConfigError as exc:
            raise UserError(str(exc)) from None
    log.info("CAN bus %s", resolved.describe())
    if config.bus.interface == "virtual":
        print(f"socd run: warning: listening on python-can's in-process 'virtual' bus {resolved.describe()}: "
              f"no other process can send to it; give -i/-c (e.g. -i socketcan -c can0), [bus] in --config, "
              f"or CAN_INTERFACE/CAN_CHANNEL", file=sys.stderr)
    try:
        daemon = Daemon(config)
    except (ProfileError, MetricsError) as exc:
        raise UserError(str(exc)) from None
    try:
        asyncio.run(daemon.run())
    except BusUnavailable as exc:
        print(f"socd run: {exc}", file=sys.stderr)
        return 1
    except MetricsError as exc:
        raise UserError(str(exc)) from None
    print(f"socd run: {stop_summary(daemon)}", file=sys.stderr)
    return 0


def stop_summary(daemon: Any) -> str:
    """One line on how a run ended: what it estimated and whether its state was saved."""
    counters = daemon.counters()
    saved = (f"state saved to {daemon.config.checkpoint.path}" if daemon.final_checkpoint_saved
             else "no state saved (nothing estimated)" if daemon.samples == 0
             else f"state NOT saved to {daemon.config.checkpoint.path} (see the log)")
    return (f"stopped after {daemon.samples} samples of {daemon.n} cells "
            f"({counters.get('frames_in', 0)} frames in, {counters.get('frames_rejected', 0)} rejected, "
            f"{counters.get('values_rejected', 0)} values rejected); {saved}")
