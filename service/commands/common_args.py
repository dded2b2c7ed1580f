"""The flags every ``socd`` command shares, defined once (like python-can's :mod:`can.cli`).

One vocabulary across commands:

==================  =====================================================================
flag                meaning
==================  =====================================================================
``--cell FILE``     cell profile (TOML/JSON from ``socd fit``)
``--soc0 SOC``      initial/known SOC, a fraction in [0, 1]
``-q/--quiet``      no progress on stderr (``--progress`` forces it when stderr is no TTY)
``--log-level``     ``debug|info|warning|error``
``--json OUT``      results as JSON to a file, or ``-`` for stdout (human text then goes to
                    stderr so stdout stays valid JSON)
``--bounds``        ``FIELD=LO:HI``, a recording column's plausibility range (commands reading recordings)
==================  =====================================================================

Older spellings still parse as hidden, deprecated aliases that say so on stderr:
``--profile`` (→ ``--cell``), ``--start-soc`` (→ ``--soc0``), ``--no-progress`` (→ ``--quiet``).

Every value is checked by an argparse ``type=`` function, so a bad value is argparse's own
one-line error naming the flag (``argument --speed: must be >= 0, got -1``), exit status 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

from service.errors import UserError

LOG_LEVELS = ("debug", "info", "warning", "error")


# ---------------------------------------------------------------------------------------
# value types (argparse ``type=``): raise ArgumentTypeError with a message that reads
# after "argument --flag: "
# ---------------------------------------------------------------------------------------
def plain_text(doc: str) -> str:
    """A docstring's reStructuredText made plain for ``--help``: ``x`` and :func:`x` become x."""
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", doc)
    return text.replace("``", "")


def _float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return x


def _int(text: str) -> int:
    try:
        return int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def positive_float(text: str) -> float:
    """A finite number > 0."""
    x = _float(text)
    if x <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return x


def non_negative_float(text: str) -> float:
    """A finite number >= 0."""
    x = _float(text)
    if x < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return x


#: the slowest replay speed-up taken (a thousandth of real time): below it a replay of seconds runs
#: for days, and a timestamp runs past what the platform's time_t holds
MIN_REPLAY_SPEED = 1e-3
MAX_REPLAY_SPEED = 1e6


def replay_speed(text: str) -> float:
    """0 (as fast as possible) or a speed-up in [:data:`MIN_REPLAY_SPEED`, :data:`MAX_REPLAY_SPEED`]."""
    x = _float(text)
    if x != 0 and not MIN_REPLAY_SPEED <= x <= MAX_REPLAY_SPEED:
        raise argparse.ArgumentTypeError(f"must be 0 (as fast as possible) or a speed-up in "
                                         f"[{MIN_REPLAY_SPEED:g}, {MAX_REPLAY_SPEED:g}], got {text}")
    return x


def finite_float(text: str) -> float:
    return _float(text)


def float_in(lo: float, hi: float, what: str) -> Callable[[str], float]:
    """A finite number in [lo, hi], called ``what`` in the error."""

    def parse(text: str) -> float:
        x = _float(text)
        if not lo <= x <= hi:
            raise argparse.ArgumentTypeError(f"must be {what} in [{lo:g}, {hi:g}], got {text}")
        return x

    parse.__name__ = what
    return parse


#: a probability in [0, 1]
probability = float_in(0.0, 1.0, "a probability")
#: a state of charge as a fraction in [0, 1] (not percent)
soc_fraction = float_in(0.0, 1.0, "a SOC fraction")
#: a lower bound of a CPE order (the search's orders end at 1; ``socd fit --min-order``)
cpe_order_bound = float_in(0.05, 0.99, "a CPE order bound")
#: a share of a resistance that a part of it keeps (``socd fit --pure-ohmic-share``)
resistance_share = float_in(0.0, 1.0, "a share of R0")


def relative_sigma(text: str) -> float:
    """σ of a cell's relative capacity or resistance, in [0, 1/3): spreads are clipped at ±3σ, so a
    larger σ gives a cell no (or a negative) capacity or resistance."""
    x = non_negative_float(text)
    if x >= 1 / 3:
        raise argparse.ArgumentTypeError(f"must be in [0, 1/3) (a cell 3σ below would have none left), got {text}")
    return x


#: σ of a start-SOC spread: three of it span the SOC range's middle half, so a wider spread puts cells
#: at 0 or 1 by clipping instead of by draw
start_soc_sigma = float_in(0.0, 0.2, "a start-SOC σ (a fraction)")
#: σ of a per-sensor temperature offset, K: three of it is a sensor 30 K off, a fault (--stuck-cell
#: and the faults group model those), not a spread
sensor_temperature_sigma = float_in(0.0, 10.0, "a sensor temperature σ in K")


def positive_int(text: str) -> int:
    n = _int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return n


def memory_length(text: str) -> int:
    """A G-L memory length: 1 to the estimators' :data:`~service.cell.memory.MAX_MEMORY_LENGTH`."""
    from service.cell.memory import MAX_MEMORY_LENGTH

    n = positive_int(text)
    if n > MAX_MEMORY_LENGTH:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_MEMORY_LENGTH} (the estimators' longest memory), got {text}")
    return n


def non_negative_int(text: str) -> int:
    n = _int(text)
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return n


def int_range(lo: int, hi: int) -> Callable[[str], int]:
    """An integer in [lo, hi]."""

    def parse(text: str) -> int:
        n = _int(text)
        if not lo <= n <= hi:
            raise argparse.ArgumentTypeError(f"must be {lo}..{hi}, got {text}")
        return n

    parse.__name__ = f"int {lo}..{hi}"
    return parse


#: a seed numpy's generators take
SEED = int_range(0, 2**32 - 1)


def stuck_cell(text: str) -> tuple[int, float]:
    """``I`` or ``I:T0``: cell index (0-based) and the time (s, >= 0) it freezes from."""
    cell, sep, t0 = text.partition(":")
    try:
        i = non_negative_int(cell.strip())
        t = non_negative_float(t0) if sep else 0.0
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected I[:T0] (cell index >= 0, start time >= 0 s), got {text!r}") from None
    return i, t


def bus_gap(text: str) -> tuple[float, float]:
    """``T0:DURATION``: start (s, >= 0) and length (s, > 0) of a silence on the bus."""
    t0, sep, dur = text.partition(":")
    try:
        if not sep:
            raise argparse.ArgumentTypeError("no ':'")
        return non_negative_float(t0), positive_float(dur)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected T0:DURATION (T0 >= 0 s, DURATION > 0 s), got {text!r}") from None


def value_bound(text: str) -> tuple[str, tuple[float, float]]:
    """``FIELD=LO:HI`` -> (field, (lo, hi)): a recording column's plausibility range."""
    from service.validation import RecordingBounds

    field, sep, rng = text.partition("=")
    lo_s, sep2, hi_s = rng.partition(":")
    known = tuple(RecordingBounds.__dataclass_fields__)
    if not sep or not sep2:
        raise argparse.ArgumentTypeError(f"expected FIELD=LO:HI (e.g. voltage_v=0:5), got '{text}'")
    if field not in known:
        raise argparse.ArgumentTypeError(f"unknown field '{field}'; one of {', '.join(known)}")
    lo, hi = finite_float(lo_s), finite_float(hi_s)
    if not lo < hi:
        raise argparse.ArgumentTypeError(f"{field}: LO must be below HI, got {lo:g}:{hi:g}")
    return field, (lo, hi)


def full_at(text: str) -> str:
    """``auto`` or a time in s (>= 0); kept as text for :func:`service.cell.truth.per_recording`."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        non_negative_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a time in s (>= 0) or 'auto', got {text!r}") from None
    return text


def _writable_place(path: Path) -> str | None:
    """Why nothing can be written at ``path`` (None if it can): the nearest existing folder above
    it must be a folder this user may write in (missing folders are made when writing)."""
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"{parent} is not a folder"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"no permission to write in {parent}"
    return None


#: the image formats matplotlib's Agg backend writes (``--plot``)
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".eps", ".ps")
PROFILE_SUFFIXES = (".toml", ".json")


def output_file(*suffixes: str) -> Callable[[str], str]:
    """A file to write (``-`` passes through for stdout): not an existing folder, in a place this
    user may write; with ``suffixes``, one of them (``.toml``, ``.json``...).  Checked before the
    command runs, so a long fit or diagnosis does not end in a write that fails."""
    def parse(text: str) -> str:
        if text == "-":
            return text
        path = Path(text)
        if not text.strip():
            raise argparse.ArgumentTypeError("an empty name; give a file name")
        if path.is_dir():
            raise argparse.ArgumentTypeError(f"{text} is a folder; give a file name")
        if path.is_fifo() or path.is_socket():
            # a write would wait, after the whole run, for a reader that may never come
            raise argparse.ArgumentTypeError(f"{text} is a pipe or socket, not a file; give a file name (or - for stdout)")
        if suffixes and path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"{text}: expected a {' or '.join(suffixes)} file")
        why = _writable_place(path)
        if why:
            raise argparse.ArgumentTypeError(f"cannot write {text}: {why}")
        return text
    return parse


def plot_file(text: str) -> Path:
    """An image to write (``--plot``): :func:`output_file` in one of :data:`PLOT_SUFFIXES`."""
    return Path(output_file(*PLOT_SUFFIXES)(text))


def output_dir(text: str) -> str:
    """A folder to write files into (made if missing): not an existing file."""
    path = Path(text)
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty name; give a folder")
    if text == "-":  # stdout elsewhere (--json -): a folder named "-" is never what was meant
        raise argparse.ArgumentTypeError("'-' is no folder; leave the flag out for stdout, or give a folder")
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file; give a folder")
    why = _writable_place(path / "x")
    if why:
        raise argparse.ArgumentTypeError(f"cannot write into {text}: {why}")
    return text


def same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file: the same path once links are resolved, or two hard links
    to one inode."""
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist yet
        return False


def refuse_overwriting_inputs(output: str | Path | None, inputs: Sequence[str | Path | None], flag: str) -> None:
    """Raise :class:`UserError` where ``output`` is one of the command's own input files (by path,
    link or hard link; a caller lists the defaults it reads too, e.g. the bundled profile): writing
    it would destroy the data the command was given."""
    if output is None or str(output) == "-":
        return
    out = Path(output)
    for given in inputs:
        if given is not None and same_file(Path(given), out):
            raise UserError(f"{flag} {output} is one of the input files; write the result elsewhere")


def refuse_shared_outputs(outputs: Sequence[tuple[str, str | Path | None]]) -> None:
    """Raise :class:`UserError` where two of a command's outputs (``(flag, path)``; ``None`` or
    ``-`` not given as a file) are one file: the second written would replace the first."""
    seen: dict[Path, str] = {}
    for flag, path in outputs:
        if path is None or str(path) == "-":
            continue
        key = Path(path).resolve()
        if key in seen:
            raise UserError(f"{flag} {path} is also {seen[key]}'s file; give each output a file of its own")
        seen[key] = flag


def refuse_repeated_inputs(paths: Sequence[str | Path]) -> None:
    """Raise :class:`UserError` where one input file is given twice, by the same path or as a copy
    with the same bytes: its data would count twice (a fit would weigh it double, and its OCV rows
    from one test would be read as two)."""
    import hashlib

    seen: dict[str, Path] = {}
    for given in paths:
        p = Path(given)
        try:
            key = hashlib.sha256(p.read_bytes()).hexdigest()
        except OSError:
            continue  # the loader names a file it cannot read
        if key in seen:
            same = "the same file as" if same_file(p, seen[key]) else "a copy of"
            raise UserError(f"{p}: {same} {seen[key]}, given before; give each recording once")
        seen[key] = p


# ---------------------------------------------------------------------------------------
# deprecated spellings
# ---------------------------------------------------------------------------------------
class _DeprecatedAlias(argparse.Action):
    """Stores like the new flag and says once on stderr that the old spelling is deprecated."""

    def __init__(self, option_strings, dest, new_flag: str, store_true: bool = False, **kw):
        self.new_flag = new_flag
        self.store_true = store_true
        if store_true:
            kw["nargs"] = 0
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"socd: warning: {option_string} is deprecated; use {self.new_flag}", file=sys.stderr)
        setattr(namespace, self.dest, True if self.store_true else values)


def _alias(parser: Any, old: str, new: str, dest: str, type: Callable | None = None,
           store_true: bool = False, metavar: str | None = None) -> None:
    parser.add_argument(old, dest=dest, action=_DeprecatedAlias, new_flag=new, store_true=store_true,
                        type=type, default=argparse.SUPPRESS, help=argparse.SUPPRESS, metavar=metavar)


# ---------------------------------------------------------------------------------------
# the shared flags
# ---------------------------------------------------------------------------------------
def cell_file(text: str) -> str:
    """A cell profile path; a name that is no file but is a bundled profile (``panasonic_18650pf``
    or ``panasonic_18650pf.toml``) is that profile, so an installed socd can use its own."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty name; give a cell profile file or a bundled profile's name")
    if Path(text).exists():
        return text
    from service.assets import profile_path

    name = text if text.endswith((".toml", ".json")) else f"{text}.toml"
    bundled = profile_path(Path(name).name)
    return str(bundled) if "/" not in text and bundled.is_file() else text


def recording_file(text: str) -> str:
    """A recording path; a bare name that is no file but names a recording shipped with socd
    (``pan18650pf_25C_US06`` or ``pan18650pf_25C_US06.csv``, :func:`service.assets.bundled_recordings`)
    is that recording, so an installed socd can run every command on the drive its demo replays."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty name; give a recording file")
    if Path(text).exists() or "/" in text:
        return text
    from service.assets import bundled_recording_named

    bundled = bundled_recording_named(text)
    return str(bundled) if bundled is not None else text


def recording_path_problem(path: Path, missing: str) -> str | None:
    """Why ``path`` is no recording to read, or None: not there (``missing``, e.g. "no such file", with
    the recording socd ships named) or not a regular file."""
    if path.is_file():
        return None
    if path.exists():
        return "not a regular file (a pipe, socket or device)"
    from service.assets import missing_file_hint

    return f"{missing}{missing_file_hint('recording')}"


def recording_help(text: str) -> str:
    """``text`` with the name of the recording socd ships, which :func:`recording_file` takes alone."""
    from service.assets import bundled_recording_names

    names = bundled_recording_names()
    return text + (f"; or the name of a recording socd ships: {', '.join(names)}" if names else "")


def add_cell_argument(parser: Any, *, required: bool = False, help: str | None = None,
                      old_profile_alias: bool = False) -> None:
    """``--cell CELL_FILE`` (``--profile`` kept as a hidden alias where it was used)."""
    parser.add_argument("--cell", metavar="CELL_FILE", type=cell_file, required=required, default=None,
                        help=(help or "cell profile (TOML/JSON) from 'socd fit'")
                        + "; or the name of a bundled one, e.g. panasonic_18650pf")
    if old_profile_alias:
        _alias(parser, "--profile", "--cell", "cell", type=cell_file, metavar="CELL_FILE")


def add_soc0_argument(parser: Any, *, help: str | None = None, old_start_soc_alias: bool = False) -> None:
    """``--soc0 SOC`` in [0, 1] (``--start-soc`` kept as a hidden alias where it was used)."""
    parser.add_argument("--soc0", type=soc_fraction, default=None, metavar="SOC",
                        help=help or "initial SOC, a fraction in [0, 1]")
    if old_start_soc_alias:
        _alias(parser, "--start-soc", "--soc0", "soc0", type=soc_fraction, metavar="SOC")


def add_fit_period_argument(parser: Any, *, what: str) -> None:
    """``--fit-period S``: recordings logged faster are block-averaged to S before ``what``
    (:mod:`service.characterisation.block_average`)."""
    from service.characterisation.block_average import DEFAULT_FIT_PERIOD_S, MAX_FIT_PERIOD_S

    parser.add_argument("--fit-period", type=float_in(0.0, MAX_FIT_PERIOD_S, "a period in seconds"),
                        default=DEFAULT_FIT_PERIOD_S, metavar="S",
                        help=f"a recording logged faster than this is block-averaged to it before {what} (default "
                        f"{DEFAULT_FIT_PERIOD_S:g} s), so the G-L memory of 16 samples spans the same time whatever "
                        "the logging rate; 0 keeps the recorded rate (a 10 Hz fit has a 1.6 s memory and generalised "
                        "worse: docs/results/characterisation.md)")


def add_progress_arguments(parser: Any, *, old_no_progress_alias: bool = False) -> None:
    """``-q/--quiet`` and ``--progress`` (progress bars on stderr even when it is no TTY)."""
    g = parser.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    g.add_argument("--progress", action="store_true",
                   help="show progress even when stderr is not a terminal (default: only on a terminal)")
    if old_no_progress_alias:
        _alias(parser, "--no-progress", "--quiet", "quiet", store_true=True)


def add_log_level_argument(parser: Any, default: str = "warning") -> None:
    parser.add_argument("--log-level", default=default, choices=LOG_LEVELS, help=f"default: {default}")


def add_json_argument(parser: Any, what: str = "the results") -> None:
    parser.add_argument("--json", metavar="OUT", default=None, type=output_file(),
                        help=f"write {what} as JSON to OUT ('-' = stdout; the text summary then goes to stderr)")


def add_bounds_argument(parser: Any) -> None:
    """``--bounds FIELD=LO:HI`` on every command that reads recordings."""
    from service.validation import DEFAULT_BOUNDS, RecordingBounds

    now = ", ".join(f"{f} {DEFAULT_BOUNDS.of(f)[0]:g}:{DEFAULT_BOUNDS.of(f)[1]:g}"
                    for f in RecordingBounds.__dataclass_fields__)
    parser.add_argument("--bounds", action="append", type=value_bound, default=None, metavar="FIELD=LO:HI",
                        help=f"plausibility range of a recording column; a value outside is refused "
                             f"with its file, row and field (repeat per field; defaults: {now})")


def add_common_arguments(parser: argparse.ArgumentParser, *, progress: bool = False, json_out: str | None = None,
                         log_level: str = "warning", old_no_progress_alias: bool = False,
                         bounds: bool = False) -> None:
    """``--log-level`` on every command; ``--quiet/--progress``, ``--json`` and ``--bounds``
    (commands that read recordings) where they apply."""
    add_log_level_argument(parser, log_level)
    if bounds:
        add_bounds_argument(parser)
    if progress:
        add_progress_arguments(parser, old_no_progress_alias=old_no_progress_alias)
    if json_out is not None:
        add_json_argument(parser, json_out)


# ---------------------------------------------------------------------------------------
# what commands do with them
# ---------------------------------------------------------------------------------------
def setup_logging(args: argparse.Namespace) -> None:
    level = getattr(args, "log_level", None) or "warning"
    logging.basicConfig(level=getattr(logging, level.upper()),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def progress_enabled(args: argparse.Namespace, stream: TextIO | None = None) -> bool:
    """Progress on stderr: never with ``--quiet``; always with ``--progress``; else only on a TTY."""
    if getattr(args, "quiet", False):
        return False
    if getattr(args, "progress", False):
        return True
    stream = stream or sys.stderr
    return bool(getattr(stream, "isatty", lambda: False)())


def json_to_stdout(args: argparse.Namespace) -> bool:
    return getattr(args, "json", None) == "-"


def text_stream(args: argparse.Namespace) -> TextIO:
    """Where a command's human-readable summary goes: stderr when stdout carries ``--json -``."""
    return sys.stderr if json_to_stdout(args) else sys.stdout


def _plain(x: Any) -> Any:
    """numpy scalars and paths as JSON values."""
    if isinstance(x, Path):
        return str(x)
    if hasattr(x, "item"):
        return x.item()
    raise TypeError(f"{type(x).__name__} is not JSON serialisable")


def finite_json(obj: Any, where: str = "") -> tuple[Any, list[str]]:
    """``obj`` with every non-finite float (NaN, ±inf: not JSON) as None, and where each was
    (``effects[0].params_std.tau_s``)."""
    if isinstance(obj, float):
        return (obj, []) if math.isfinite(obj) else (None, [where or "(the value)"])
    if isinstance(obj, dict):
        items = [(k, finite_json(v, f"{where}.{k}" if where else str(k))) for k, v in obj.items()]
        return {k: v for k, (v, _) in items}, [w for _, (_, ws) in items for w in ws]
    if isinstance(obj, (list, tuple)):
        parts = [finite_json(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        return [v for v, _ in parts], [w for _, ws in parts for w in ws]
    return obj, []


#: how many of the non-finite values' places a warning names
NAMED_NOT_FINITE = 4


def write_json(dest: str | None, obj: Any) -> None:
    """Write ``obj`` as JSON to ``dest`` (a path, ``-`` for stdout, None for nowhere); a value that is
    not finite (a model that diverged, a figure the data cannot give) is written as null, and a warning
    names where."""
    if dest is None:
        return
    obj, not_finite = finite_json(json.loads(json.dumps(obj, default=_plain)))
    if not_finite:
        named = ", ".join(not_finite[:NAMED_NOT_FINITE]) + (", ..." if len(not_finite) > NAMED_NOT_FINITE else "")
        print(f"socd: warning: {len(not_finite)} value(s) in the JSON were not finite (NaN or infinity) and are "
              f"written as null: {named}", file=sys.stderr)
    text = json.dumps(obj, indent=1, allow_nan=False)
    if dest == "-":
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
        return
    path = Path(dest)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")
    except OSError as exc:  # a full disk, a device, a folder made read-only after the check
        raise UserError(f"{path}: cannot write the JSON: {exc.strerror or exc}") from None
