"""One CLI vocabulary: every bad flag value is argparse's error naming the flag (exit 2), on
every command; old spellings still work as deprecated aliases; ``--json -`` keeps stdout JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from service.cli import build_parser, main

ROOT = Path(__file__).resolve().parent.parent
PROFILE = ROOT / "configs" / "cells" / "panasonic_18650pf.toml"

#: (argv, flag the error must name)
BAD_VALUES = [
    (["replay", "x.log", "--speed", "-1"], "--speed"),
    (["replay", "x.log", "--stuck-cell", "abc"], "--stuck-cell"),
    (["replay", "x.log", "--stuck-cell", "3:-5"], "--stuck-cell"),
    (["replay", "x.log", "--bus-gap", "10"], "--bus-gap"),
    (["replay", "x.log", "--bus-gap", "10:0"], "--bus-gap"),
    (["replay", "x.log", "--soc0", "2"], "--soc0"),
    (["replay", "x.log", "--start-soc", "2"], "--start-soc"),
    (["replay", "x.log", "--drop", "1.5"], "--drop"),
    (["replay", "x.log", "--jitter", "nan"], "--jitter"),
    (["replay", "x.log", "--cells", "0"], "--cells"),
    (["replay", "x.log", "--loop", "0"], "--loop"),
    (["replay", "x.log", "--spread-soc", "-0.1"], "--spread-soc"),
    (["replay", "x.log", "--log-level", "loud"], "--log-level"),
    (["run", "--max-bus-retries", "-1"], "--max-bus-retries"),
    (["run", "-i", "no_such_interface"], "--interface"),
    (["run", "--bitrate", "fast"], "--bitrate"),
    (["evaluate", "r.csv", "--cell", "c.toml", "--init-soc-error", "1.5"], "--init-soc-error"),
    (["evaluate", "r.csv", "--cell", "c.toml", "--current-bias-c", "0.9"], "--current-bias-c"),
    (["diagnose", "r.csv", "--cell", "c.toml", "--soc0", "-0.1"], "--soc0"),
    (["diagnose", "r.csv", "--cell", "c.toml", "--fit-fraction", "0.95"], "--fit-fraction"),
    (["diagnose", "r.csv", "--ocv", "o.csv", "--capacity-ah", "0"], "--capacity-ah"),
    (["diagnose", "r.csv", "--cell", "c.toml", "--nominal-ambient-c", "warm"], "--nominal-ambient-c"),
    (["evaluate", "r.csv", "--cell", "c.toml", "--full-at", "soon"], "--full-at"),
    (["fit", "r.csv", "--capacity-ah", "2", "--full-at", "-3", "-o", "x.toml"], "--full-at"),
    (["fit", "r.csv", "--capacity-ah", "-2", "-o", "x.toml"], "--capacity-ah"),
    (["fit", "r.csv", "--capacity-ah", "2", "--memory-length", "0", "-o", "x.toml"], "--memory-length"),
    (["fit", "r.csv", "--capacity-ah", "2", "--starts", "0", "-o", "x.toml"], "--starts"),
    (["bench", "--cells", "abc"], "--cells"),
    (["bench", "--steps", "3"], "--steps"),
    (["demo", "--speed", "-1"], "--speed"),
    (["demo", "--cells", "999"], "--cells"),
    (["demo", "--soc0", "1.2"], "--soc0"),
    (["demo", "--seconds", "0"], "--seconds"),
    (["watch", "--sort", "colour"], "--sort"),
    (["watch", "--timeout", "-3"], "--timeout"),
]


@pytest.mark.parametrize(("argv", "flag"), BAD_VALUES, ids=[" ".join(a) for a, _ in BAD_VALUES])
def test_bad_value_is_an_argparse_error_naming_the_flag(argv, flag, capsys) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err, "no error message"
    last = err[-1]
    assert last.startswith(f"socd {argv[0]}: error: argument ") and flag in last, last
    assert "Traceback" not in "\n".join(err)


def test_shared_flags_are_spelled_the_same_everywhere() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")  # the subparsers action
    options = {name: {o for a in p._actions for o in a.option_strings} for name, p in sub.choices.items()}
    for name, opts in options.items():
        assert "--log-level" in opts, name
    for name in ("evaluate", "diagnose", "replay"):
        assert {"--quiet", "-q", "--progress"} <= options[name], name
    for name in ("evaluate", "diagnose", "bench", "demo"):
        assert "--json" in options[name], name
    for name in ("evaluate", "diagnose", "bench", "replay"):
        assert "--cell" in options[name], name
    for name in ("diagnose", "replay", "demo"):
        assert "--soc0" in options[name], name
    # the old spellings parse but are not advertised
    help_text = sub.choices["replay"].format_help()
    assert "--profile" not in help_text and "--start-soc" not in help_text and "--no-progress" not in help_text
    assert "--cell" in help_text and "--soc0" in help_text and "--quiet" in help_text


def test_deprecated_aliases_store_the_new_flag_and_say_so(capsys) -> None:
    parser = build_parser()
    args = parser.parse_args(["replay", "x.csv", "--profile", "p.toml", "--start-soc", "0.5", "--no-progress"])
    assert args.cell == "p.toml" and args.soc0 == 0.5 and args.quiet is True
    err = capsys.readouterr().err
    for old, new in (("--profile", "--cell"), ("--start-soc", "--soc0"), ("--no-progress", "--quiet")):
        assert f"{old} is deprecated; use {new}" in err
    args = parser.parse_args(["demo", "--start-soc", "0.9"])
    assert args.soc0 == 0.9


def test_quiet_and_progress_exclude_each_other(capsys) -> None:
    assert main(["replay", "x.log", "--quiet", "--progress"]) == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_json_dash_keeps_stdout_json() -> None:
    """``--json -``: the JSON document alone on stdout, the human summary on stderr (a subprocess:
    bench pins its process to one CPU)."""
    proc = subprocess.run([sys.executable, "-m", "service.cli", "bench", "--cells", "2", "--steps", "10",
                           "--reference-steps", "2", "--cell", str(PROFILE), "--json", "-"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    out, err = proc.stdout, proc.stderr
    doc = json.loads(out)
    assert doc["cells"] == 2 and doc["cell_steps_per_s"] > 0
    assert "vectorised pipeline" in err


def test_progress_is_off_when_stderr_is_not_a_terminal(capsys) -> None:
    from service.commands.common_args import progress_enabled

    parser = build_parser()
    assert not progress_enabled(parser.parse_args(["replay", "x.log"]))  # pytest's stderr is no TTY
    assert progress_enabled(parser.parse_args(["replay", "x.log", "--progress"]))
    assert not progress_enabled(parser.parse_args(["replay", "x.log", "-q"]))


def test_forced_progress_draws_a_bar_with_eta(tmp_path: Path) -> None:
    from service.commands.progress import progress_bar

    log = tmp_path / "progress.txt"
    with log.open("w") as stream, progress_bar(True, "work", 4, unit="steps", stream=stream) as bar:
        for _ in range(4):
            bar.advance(1)
    text = log.read_text()
    assert "work" in text and "4/4" in text and "ETA" in text


def test_cell_names_a_bundled_profile_when_no_such_file(tmp_path, monkeypatch) -> None:
    """An installed socd can use its own profiles by name; a real file of that name wins."""
    from service.assets import profile_path
    from service.commands.common_args import cell_file

    monkeypatch.chdir(tmp_path)
    assert cell_file("panasonic_18650pf") == str(profile_path("panasonic_18650pf.toml"))
    assert cell_file("calce_a123.toml") == str(profile_path("calce_a123.toml"))
    assert cell_file("no_such_cell") == "no_such_cell"  # load_profile then names the missing file
    assert cell_file("sub/panasonic_18650pf") == "sub/panasonic_18650pf"  # a path is never replaced
    own = tmp_path / "panasonic_18650pf.toml"
    own.write_text("x")
    assert cell_file("panasonic_18650pf.toml") == "panasonic_18650pf.toml"


def test_a_recording_socd_ships_is_taken_by_its_name(tmp_path, monkeypatch, capsys) -> None:
    """An installed socd runs evaluate, fit, diagnose and replay on the drive its demo replays by name;
    a file of that name in the working folder wins, a path is never replaced, and a missing
    recording's error names the one socd ships."""
    from service.assets import bundled_recording
    from service.commands.common_args import recording_file

    monkeypatch.chdir(tmp_path)
    shipped = bundled_recording()
    assert recording_file(shipped.stem) == str(shipped)
    assert recording_file(shipped.name) == str(shipped)
    assert recording_file("no_such_drive") == "no_such_drive"
    assert recording_file(f"sub/{shipped.name}") == f"sub/{shipped.name}"
    (tmp_path / shipped.name).write_text("x")
    assert recording_file(shipped.name) == shipped.name

    for argv in (["evaluate", "--cell", "panasonic_18650pf"], ["replay", "--no-send"]):
        parsed = build_parser().parse_args([*argv, shipped.stem])
        assert str(shipped) in (getattr(parsed, "recordings", None) or [getattr(parsed, "input", None)])

    assert main(["evaluate", "--cell", "panasonic_18650pf", "-q", "missing_drive.csv"]) == 2
    err = capsys.readouterr().err
    assert "missing_drive.csv: cannot read recording: no such file" in err and shipped.stem in err
