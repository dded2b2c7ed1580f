"""Every command's ``--help`` explains every option in plain text."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from service import assets
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


def test_the_results_a_help_text_cites_are_installed_where_the_help_says(monkeypatch) -> None:
    """`socd fit --help` cited docs/results/tuning.md and others, which the wheel did not ship, and no
    help said where a user without the source checkout would find them."""
    helps = {"socd": build_parser().format_help(), **{n: p.format_help() for n, p in _commands().items()}}
    cited = {name for text in helps.values() for name in re.findall(r"docs/results/([a-z_]+\.md)", text)}
    assert {"tuning.md", "characterisation.md", "cell_options.md"} <= cited
    assert all((assets.results_dir() / name).is_file() for name in cited), sorted(cited)

    # the note names the installed folder whole, however long and hyphenated its path and narrow the terminal
    installed = Path("/opt/venvs/bms-tools/lib/python3.11/site-packages/service/assets/results")
    monkeypatch.setattr(assets, "results_dir", lambda: installed)
    monkeypatch.setenv("COLUMNS", "50")
    helps = {"socd": build_parser().format_help(), **{n: p.format_help() for n, p in _commands().items()}}
    citing = sorted(n for n, text in helps.items() if "docs/results/" in text)
    assert {"socd", "fit", "diagnose"} <= set(citing)
    assert [n for n in citing if f"{installed}/NAME.md" not in helps[n]] == []
