"""Every command's ``--help`` explains every option in plain text."""

from __future__ import annotations

import argparse

from service.cli import build_parser


def _commands() -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_every_option_of_every_command_has_a_help_text() -> None:
    """`socd diagnose --seed` had none."""
    missing = [f"{name} {'/'.join(a.option_strings) or a.dest}" for name, p in _commands().items()
               for a in p._actions if a.help is None and not isinstance(a, argparse._HelpAction)]
    assert missing == []


def test_no_help_text_shows_rst_markup() -> None:
    """`replay`, `diagnose` and `schema` printed ``socd replay`` with its double backticks."""
    marked = [name for name, p in _commands().items()
              if any(m in p.format_help() for m in ("``", ":func:`", ":mod:`", ":class:`"))]
    assert marked == []
