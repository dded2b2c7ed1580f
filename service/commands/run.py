"""``socd run --config FILE``: the estimator service (see :mod:`service.daemon.daemon`)."""

from __future__ import annotations

import argparse
import asyncio
import logging
from pathlib import Path

from service.cli import UserError

LOG_LEVELS = ("debug", "info", "warning", "error")


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run the estimator service on a CAN bus",
        description=(
            "Read the BMS bus, estimate each cell's SOC and parameters, publish them on CAN "
            "and Zenoh; checkpoint the estimator state and restore it on start. "
            "SIGTERM/SIGINT write a final checkpoint and exit cleanly."
        ),
    )
    parser.add_argument("--config", required=True, type=Path, metavar="FILE", help="socd TOML config")
    parser.add_argument("--log-level", default="info", choices=LOG_LEVELS, help="default: info")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from service.cell.profile import ProfileError
    from service.config import ConfigError, load_config
    from service.daemon.daemon import Daemon

    logging.basicConfig(
        level=getattr(logging, args.log_level.upper()),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    try:
        daemon = Daemon(config)
    except ProfileError as exc:
        raise UserError(str(exc)) from None
    asyncio.run(daemon.run())
    return 0
