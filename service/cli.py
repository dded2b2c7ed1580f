"""The ``socd`` command line: a registry of subcommands, one module each.

Like cantools' ``subparsers/``, a subcommand whose module fails to import (a missing
optional dependency, say) registers a stand-in that reports the import error, so one
broken command never breaks the others.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import textwrap
from typing import NoReturn

from service import __version__
from service.assets import RESULTS_CITATION, results_note
from service.errors import MissingExtra, UserError
from service.extras import missing_extra
from service.validation import use_bounds

__all__ = ["SUBCOMMANDS", "UserError", "build_parser", "main"]

#: subcommand name -> module that defines ``add_subparser(subparsers)``
SUBCOMMANDS: dict[str, str] = {
    "demo": "service.commands.demo",
    "run": "service.commands.run",
    "replay": "replay.cli",
    "watch": "service.commands.watch",
    "fit": "service.commands.fit",
    "evaluate": "service.commands.evaluate",
    "bench": "service.commands.bench",
    "diagnose": "service.commands.diagnose",
    "check": "service.commands.check",
    "schema": "service.commands.schema",
}


class _WholePaths(argparse.HelpFormatter):
    """Fills a description or epilog as argparse does, but never breaks a long word or a hyphenated
    one across lines, so a path in it (``.../site-packages/...``) can be copied whole."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return textwrap.fill(" ".join(text.split()), width, initial_indent=indent, subsequent_indent=indent,
                             break_long_words=False, break_on_hyphens=False)


class _Parser(argparse.ArgumentParser):
    """argparse's parser, with its usage errors in one line (``socd fit: error: argument --capacity-ah:
    must be > 0, got -1``) as socd's other errors are, not under the usage block (17 lines for fit)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _register_broken(subparsers: argparse._SubParsersAction, name: str, exc: BaseException) -> None:
    reason = missing_extra(exc) or f"unavailable because its module failed to import: {exc}"
    # a module that failed half-way may have added its parser already: reuse it (a second one
    # with the same name is an argparse error that would take every other command down with it)
    parser = subparsers.choices.get(name) or subparsers.add_parser(name, help=f"(unavailable: {reason})")

    def _fail(_args: argparse.Namespace) -> int:
        print(f"socd {name}: {reason}", file=sys.stderr)
        return 3

    parser.set_defaults(func=_fail)


def named_command(argv: list[str]) -> str | None:
    """The subcommand ``argv`` names (its first word that is not a flag), or None when it names
    none socd has (``socd --help``, ``socd --version``, a misspelt command)."""
    for word in argv:
        if word in ("-h", "--help"):  # socd's own help lists every command
            return None
        if not word.startswith("-"):
            return word if word in SUBCOMMANDS else None
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """socd's parser with every subcommand, or with ``command``'s alone: what running it needs.
    Each command's module is imported to build its parser, and ``socd run``'s and ``socd replay``'s
    import python-can, which loads asammdf and pandas where the ``mf4`` extra is installed, so ``socd
    evaluate`` does not build them."""
    parser = _Parser(
        prog="socd",
        description=(
            "Battery state estimator: multi-time-scale fractional-order model with online "
            "identification and FO-MI-UKF, served over CAN and Zenoh."
        ),
        epilog=results_note(),
        formatter_class=_WholePaths,
    )
    parser.add_argument("--version", action="version", version=f"socd {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in SUBCOMMANDS.items():
        if command is not None and name != command:
            continue
        try:
            module = importlib.import_module(module_name)
            module.add_subparser(subparsers)
        except Exception as exc:  # noqa: BLE001 - reported through the stand-in command
            _register_broken(subparsers, name, exc)
    for sub in subparsers.choices.values():
        # a command whose help cites docs/results/ says where an installed socd keeps it
        # (read from the texts as written: a narrow terminal's help wraps a citation apart)
        if any(RESULTS_CITATION in (text or "") for text in [sub.description, *(a.help for a in sub._actions)]):
            sub.epilog = f"{sub.epilog}\n\n{results_note()}" if sub.epilog else results_note()
            if sub.formatter_class is argparse.HelpFormatter:
                sub.formatter_class = _WholePaths
    return parser


def _command_parser(parser: argparse.ArgumentParser, command: str | None) -> argparse.ArgumentParser | None:
    """The parser of ``command`` (``socd run``'s), or None."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices.get(command) if command else None
    return None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(named_command(argv))
    try:
        args, unknown = parser.parse_known_args(argv)
        if unknown:  # named by the command's parser (socd run: error: ...), not the top level's (socd: ...)
            (_command_parser(parser, getattr(args, "command", None)) or parser).error(
                f"unrecognized arguments: {' '.join(unknown)}")
    except SystemExit as exc:  # argparse's own error (exit 2, flag named on stderr), --help, --version
        return exc.code if isinstance(exc.code, int) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        if getattr(args, "bounds", None):  # --bounds: the ranges every recording loader checks
            use_bounds(dict(args.bounds))
        return int(args.func(args) or 0)
    except MissingExtra as exc:
        print(f"socd {args.command}: error: {exc}", file=sys.stderr)
        return 3
    except UserError as exc:
        print(f"socd {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:
        # an optional dependency a command imports when it runs: name the extra, no traceback
        hint = missing_extra(exc)
        if hint is None:
            raise
        print(f"socd {args.command}: {hint}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # whoever read our stdout went away (`socd diagnose ... | head`): stop quietly, as a
        # shell tool does on SIGPIPE; point stdout at /dev/null so the exit flush cannot fail again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as exc:
        # a file the command could not write or read (permissions, a full disk, a special file
        # system): the path and the reason, not a traceback
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"socd {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    # run through the importable module so UserError is the class the commands raise
    from service.cli import main as _main

    sys.exit(_main())
