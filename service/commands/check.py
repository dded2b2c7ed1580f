"""``socd check --config FILE``: validate a config and its DBC mapping without starting anything.

Exit 0 with a one-screen summary, or 2 with one line per problem (``FILE: field: problem``):
the config's fields (pydantic), both DBCs, every mapped signal in the input DBC (with a
close name when there is one), multiplexed signals (a mapped signal must not be a
multiplexer switch, and its multiplexer values must fit the switch signal), the output
DBC's frames, cell indices and temperature coverage, the cell profile, the bus interface
name, the Zenoh config file and whether the checkpoint's folder takes a new file.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service.commands.common_args import add_common_arguments, plain_text, setup_logging


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "check",
        help="validate a config and its DBC mapping (exit 0 with a summary, 2 with every problem)",
        description=plain_text(__doc__.split("\n\n")[1]),
    )
    p.add_argument("--config", type=Path, metavar="FILE", help="socd TOML config (default: the bundled default)")
    add_common_arguments(p)
    p.set_defaults(func=run)


@dataclass
class CheckResult:
    """Problems (one line each) and, when there are none, the summary lines."""

    source: str
    problems: list[str] = field(default_factory=list)
    summary: list[str] = field(default_factory=list)

    def problem(self, where: str, text: str) -> None:
        self.problems.append(f"{self.source}: {where}: {text}")

    @property
    def ok(self) -> bool:
        return not self.problems


def check_config(path: Path | None) -> CheckResult:
    """Every problem of the config at ``path`` (the bundled default when None)."""
    from service.config import DEFAULT_CONFIG, ConfigError, find_config, load_config

    source = str(path if path is not None else DEFAULT_CONFIG)
    res = CheckResult(source)
    read = find_config(path)
    try:
        config = load_config(read, check_files=False)
    except ConfigError as exc:
        res.problems.extend(str(exc).splitlines())
        return res
    dbs = _check_dbcs(config, res)
    if "input" in dbs:
        _check_mapping(config, dbs["input"], res)
    if "output" in dbs and config.output.can_enabled:
        _check_output(dbs["output"], config.pack.n_cells, res)
    profile = _check_profile(config, res)
    _check_bus(config, res)
    _check_zenoh(config, res)
    _check_checkpoint(config, res)
    if res.ok:
        res.summary = _summary(config, dbs, profile)
        if path is not None and read != Path(path).expanduser():
            res.summary.insert(0, f"config        {read} (socd's example of that name)")
    return res


def _check_dbcs(config: Any, res: CheckResult) -> dict[str, Any]:
    from service.config import dbc_load_problem, load_dbc, shared_frame_id

    dbs = {}
    for which in ("input", "output"):
        p = getattr(config.dbc, which)
        try:
            db = load_dbc(p)
        except FileNotFoundError:
            res.problem(f"dbc.{which}", f"no such file {p}")
            continue
        except Exception as exc:  # noqa: BLE001 - cantools raises many kinds for a bad file
            res.problem(f"dbc.{which}", f"cannot load DBC {p}: {dbc_load_problem(exc)}")
            continue
        if (twice := shared_frame_id(db)) is not None:
            res.problem(f"dbc.{which}", twice)
            continue
        dbs[which] = db
    return dbs


def _check_mapping(config: Any, db: Any, res: CheckResult) -> None:
    from service.config import mapping_problems

    for where, why in mapping_problems(config, db):
        res.problem(where, why)


def _check_output(db: Any, n_cells: int, res: CheckResult) -> None:
    from service.config import OUTPUT_MESSAGES, output_range_problems

    for msg_name, sig_names in OUTPUT_MESSAGES.items():
        try:
            msg = db.get_message_by_name(msg_name)
        except KeyError:
            res.problem("dbc.output", f"message {msg_name!r} missing")
            continue
        have = {s.name for s in msg.signals}
        for s in sig_names:
            if s not in have:
                res.problem("dbc.output", f"signal {s!r} missing from {msg_name}")
    if res.ok:
        for problem in output_range_problems(db, n_cells):
            res.problem("dbc.output", problem)


def _check_profile(config: Any, res: CheckResult) -> Any:
    from service.cell.profile import ProfileError, load_profile

    try:
        return load_profile(config.cell_profile)
    except ProfileError as exc:
        res.problem("cell_profile", str(exc))
    except Exception as exc:  # noqa: BLE001 - a profile that parses but does not build
        res.problem("cell_profile", f"{config.cell_profile}: {exc}")
    return None


def _check_bus(config: Any, res: CheckResult) -> None:
    from service.bus.cli_args import BusConfigError, check_interface

    try:
        check_interface(config.bus.interface, "bus.interface")
    except BusConfigError as exc:
        res.problem("bus.interface", str(exc).split(": ", 1)[1])


def _check_zenoh(config: Any, res: CheckResult) -> None:
    if config.zenoh.config_file is None:
        return
    from service.daemon.zenoh_pub import ZenohConfigError, config_from_section

    try:
        config_from_section(config.zenoh)
    except ZenohConfigError as exc:
        res.problem("zenoh.config_file", str(exc).split(": ", 1)[1])


def _check_checkpoint(config: Any, res: CheckResult) -> None:
    from service.config import override_of
    from service.daemon.checkpoint import checkpoint_write_problem

    if (problem := checkpoint_write_problem(config.checkpoint.path)) is not None:
        env = override_of("checkpoint", "path")
        res.problem("checkpoint.path", problem + (f" (the path is {env}'s, which overrides the file)" if env else ""))


def _summary(config: Any, dbs: dict[str, Any], profile: Any) -> list[str]:
    m, n = config.mapping, config.pack.n_cells
    db_in = dbs["input"]
    names = {name for _, name in m.all_signals()}
    used = sorted({msg.name for msg in db_in.messages if names & {s.name for s in msg.signals}})
    z = config.zenoh
    lines = [
        f"pack          {n} cells, {len(m.temperature_signals)} temperature sensor(s), current "
        f"{m.current_signal} (sign {m.current_sign:+g})",
        f"input DBC     {config.dbc.input} ({len(db_in.messages)} messages; mapped: {', '.join(used)})",
        "clock         " + (f"sample time from {m.time_signal} (time sync), not frame arrival"
                            if m.time_signal else "frame timestamps"),
        f"output DBC    {config.dbc.output} "
        + ("(CAN output on)" if config.output.can_enabled else "(CAN output off)"),
        f"cell profile  {config.cell_profile} ({profile.name}, {profile.capacity_ah:g} Ah)",
        f"bus           {_bus_line(config.bus)}",
        "zenoh         " + (f"{z.mode}, listen {', '.join(z.listen) or 'nowhere'}, keys {z.key_prefix}/{z.pack_id}/..."
                            + (f", config file {z.config_file}" if z.config_file else "")
                            if config.output.zenoh_enabled else "off"),
        "metrics       " + (f"http://{config.metrics.host}:{config.metrics.port}/metrics"
                            if config.metrics.enabled else "off"),
        f"checkpoint    {config.checkpoint.path} every {config.checkpoint.interval_s:g} s",
    ]
    return lines


def _bus_line(b: Any) -> str:
    text = f"{b.interface}:{b.channel}"
    if b.bitrate and b.interface != "virtual":
        text += f" @ {b.bitrate} bit/s"
    if b.max_open_retries:
        return text + f", gives up after {b.max_open_retries} failed opens in a row"
    return text + ", retries opening for ever"


def run(args: argparse.Namespace) -> int:
    setup_logging(args)
    res = check_config(args.config)
    if not res.ok:
        for line in res.problems:
            print(line, file=sys.stderr)
        return 2
    print(f"{res.source}: OK")
    for line in res.summary:
        print("  " + line)
    return 0
