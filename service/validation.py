"""One validation layer for every file a command reads (DESIGN §6: exit 2, one line).

Recordings (:func:`service.recording.load_recording`), OCV tables
(:func:`service.cell.ocv.load_ocv_csv`), python-can logs (``socd replay``), configs and
their input DBC (:func:`service.config.check_input_mapping`) all pass through here before a
command does any work or writes anything:

- :func:`read_text`: the file exists, is readable, is text (no NUL byte, valid UTF-8; a
  byte-order mark is dropped);
- :func:`check_values`: every value finite and inside physical plausibility bounds
  (:class:`RecordingBounds`, replaceable per call), naming the first bad row and field;
- :func:`check_increasing`: time strictly increasing, naming the row;
- :func:`check_can_log`: a python-can log of a known format that reads to the end and
  holds at least one frame, every timestamp finite.

Problems raise :class:`InputFileError` (a ``ValueError``), whose message is one line
starting with the file's name; commands turn it into their one-line error with exit 2.
"""

from __future__ import annotations

import codecs
import gc
import logging
import math
import struct
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np


class InputFileError(ValueError):
    """A file given to a command cannot be used; the message names the file, row and field."""


def read_text(path: str | Path, what: str) -> str:
    """The text of ``path`` (a ``what``: "recording", "OCV table", ...), or :class:`InputFileError`."""
    path = Path(path)
    if not path.exists():
        from service.assets import missing_file_hint

        raise InputFileError(f"{path}: cannot read {what}: no such file{missing_file_hint(what)}")
    if not path.is_file():
        raise InputFileError(f"{path}: cannot read {what}: not a file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    nul = data.find(b"\x00")
    if nul >= 0:
        raise InputFileError(f"{path}: not a text file ({what} expected): NUL byte at {nul}")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path}: not a UTF-8 text {what} (invalid byte at {exc.start})") from None
    # any line ending (CRLF from Windows, a bare CR from old Mac tools) reads as one
    return text.replace("\r\n", "\n").replace("\r", "\n")


def header_text(header: Sequence[str]) -> str:
    """A CSV header as an error message shows it: on one line (quoted, so a quoted field's line
    break or tab reads as ``\\n`` / ``\\t``), at most 120 characters of it; ``(empty)`` for none."""
    joined = ",".join(header)[:120]
    return repr(joined) if joined else "(empty)"


def separator_problem(header: Sequence[str]) -> str | None:
    """What is wrong where a CSV header read at commas is one field split by ';' or tabs (a spreadsheet's
    export in a locale with a decimal comma), or None."""
    if len(header) != 1:
        return None
    sep = next((name for char, name in ((";", "';'"), ("\t", "tabs")) if char in header[0]), None)
    if sep is None:
        return None
    return (f"row 1: the fields are separated by {sep}, not commas; socd reads comma-separated values with a '.' "
            f"decimal point (header is {header_text(header)})")


def check_text_file(path: str | Path, what: str, chunk_bytes: int = 1 << 20) -> str:
    """Like :func:`read_text`, streamed (for logs that may not fit in memory); returns the first line."""
    path = Path(path)
    read_bytes_check(path, what)
    decoder = codecs.getincrementaldecoder("utf-8-sig")()
    first: str | None = None
    head = ""
    offset = 0
    try:
        with path.open("rb") as fh:
            while chunk := fh.read(chunk_bytes):
                nul = chunk.find(b"\x00")
                if nul >= 0:
                    raise InputFileError(f"{path}: not a text file ({what} expected): NUL byte at {offset + nul}")
                try:
                    text = decoder.decode(chunk)
                except UnicodeDecodeError as exc:
                    raise InputFileError(
                        f"{path}: not a UTF-8 text {what} (invalid byte at {offset + exc.start})") from None
                if first is None:
                    head += text
                    if "\n" in head:
                        first = head.split("\n", 1)[0]
                offset += len(chunk)
            decoder.decode(b"", final=True)
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: not a UTF-8 text {what} (truncated character at the end)") from None
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    return head if first is None else first


@dataclass(frozen=True)
class RecordingBounds:
    """Physical plausibility bounds of one cell's recorded values (inclusive).

    Wide enough for any lithium cell on a lab cycler; a value outside is a unit mix-up
    (mV for V, % for a fraction), a placeholder (±1e308, -999) or a corrupt file, and would
    otherwise flow silently into a fit or a score.  Pass your own to the loaders to change them.
    """

    time_s: tuple[float, float] = (-1e10, 1e10)
    current_a: tuple[float, float] = (-1000.0, 1000.0)
    voltage_v: tuple[float, float] = (0.5, 6.0)  # 0 V is a dropped sensor or an empty column
    temperature_c: tuple[float, float] = (-60.0, 150.0)
    soc_true: tuple[float, float] = (-0.5, 1.5)

    def of(self, field: str) -> tuple[float, float] | None:
        return getattr(self, field, None)


DEFAULT_BOUNDS = RecordingBounds()


def use_bounds(overrides: Mapping[str, tuple[float, float]]) -> RecordingBounds:
    """Replace some fields of the bounds every loader checks against by default (the
    commands' ``--bounds FIELD=LO:HI``); returns the bounds now in use."""
    global DEFAULT_BOUNDS
    unknown = sorted(set(overrides) - set(RecordingBounds.__dataclass_fields__))
    if unknown:
        raise ValueError(f"unknown bound field(s) {', '.join(unknown)}; known: "
                         + ", ".join(RecordingBounds.__dataclass_fields__))
    DEFAULT_BOUNDS = replace(DEFAULT_BOUNDS, **{k: (float(lo), float(hi)) for k, (lo, hi) in overrides.items()})
    return DEFAULT_BOUNDS


def check_values(path: str | Path, columns: Mapping[str, np.ndarray],
                 bounds: RecordingBounds | Mapping[str, tuple[float, float]] | None = None, first_row: int = 2) -> None:
    """Every value finite and within ``bounds`` (per field name; fields without bounds: finite only);
    else the first offending row (file line) and field."""
    bounds = DEFAULT_BOUNDS if bounds is None else bounds
    worst: tuple[int, str, str] | None = None
    for name, values in columns.items():
        v = np.asarray(values, dtype=float)
        bad = ~np.isfinite(v)
        lim = bounds.get(name) if isinstance(bounds, Mapping) else bounds.of(name)
        if lim is not None:
            with np.errstate(invalid="ignore"):
                out = (v < lim[0]) | (v > lim[1])
            bad = bad | out
        if bad.any():
            k = int(np.argmax(bad))
            why = (f"{float(v[k])!r} is not a finite number" if not math.isfinite(v[k])
                   else f"{v[k]:g} is outside the plausible range [{lim[0]:g}, {lim[1]:g}]")  # type: ignore[index]
            if worst is None or k < worst[0]:
                worst = (k, name, why)
    if worst is not None:
        k, name, why = worst
        raise InputFileError(f"{path}: row {k + first_row}: {name}: {why}")


def check_increasing(path: str | Path, t: np.ndarray, field: str = "time_s", first_row: int = 2) -> None:
    """``t`` strictly increasing; else the first row where it is not."""
    step = np.diff(np.asarray(t, dtype=float))
    if step.size and (step <= 0).any():
        k = int(np.argmax(step <= 0)) + 1
        raise InputFileError(f"{path}: row {k + first_row}: {field} does not increase ({t[k - 1]:g} then {t[k]:g})")


#: s: the longest step between two samples of one recording (a week's pause; longer is two
#: recordings joined, or a corrupt time column)
MAX_TIME_STEP_S = 7 * 86400.0
#: s and A: a step longer than an hour over which a current is held (each sample's current is held
#: over the interval before it) counts charge no sample saw: a logger that stopped under load
MAX_LOADED_STEP_S = 3600.0
HELD_CURRENT_A = 0.01


def check_time_steps(path: str | Path, t: np.ndarray, current_a: np.ndarray, first_row: int = 2) -> None:
    """No pause longer than :data:`MAX_TIME_STEP_S`, and none longer than :data:`MAX_LOADED_STEP_S`
    with a current held over it; else the first row where there is one."""
    step = np.diff(np.asarray(t, dtype=float))
    held = np.abs(np.asarray(current_a, dtype=float)[1:])
    bad = (step > MAX_TIME_STEP_S) | ((step > MAX_LOADED_STEP_S) & (held > HELD_CURRENT_A))
    if not bad.any():
        return
    k = int(np.argmax(bad))
    what = (f"{held[k]:g} A held over it would count {held[k] * step[k] / 3600:.3g} Ah that no sample saw"
            if held[k] > HELD_CURRENT_A else f"longer than {MAX_TIME_STEP_S / 86400:g} days")
    raise InputFileError(f"{path}: row {k + 1 + first_row}: time_s jumps by {step[k]:g} s ({what}): "
                         "split the recording there")


#: the header python-can writes (and its CSV reader expects) in a CSV log
PYTHON_CAN_CSV_HEADER = "timestamp,arbitration_id,extended,remote,error,dlc,data"
#: log formats that are text (checked with :func:`read_text` before python-can parses them)
TEXT_LOG_SUFFIXES = (".asc", ".csv", ".log", ".trc")
#: a CAN timestamp beyond this (s; epoch time is ~1.7e9) is corrupt
MAX_LOG_TIMESTAMP_S = 1e11
#: a frame this far (s) before an earlier frame of the log is out of order, not jitter between channels
MAX_LOG_STEP_BACK_S = 1.0


def check_can_log(path: str | Path, suffixes: Sequence[str],
                  frames: Callable[[Path], Iterable[Any]] | None = None) -> int:
    """Read a python-can log to the end; return its frame count, or raise :class:`InputFileError`.

    Catches what python-can's readers raise on files they cannot parse (``ValueError``,
    ``struct.error``, ``UnicodeDecodeError``, ...), an empty or unparsable text log that
    reads as zero frames, non-finite timestamps, and timestamps that go back by more than
    :data:`MAX_LOG_STEP_BACK_S` (the player would send such frames at once, out of time).  A ``.gz`` log is read through
    ``frames`` (the caller's reader; default ``can.LogReader``) and its text is not
    checked before decompression.
    """
    import can

    path = Path(path)
    names = [s.lower() for s in path.suffixes]
    gz = bool(names) and names[-1] == ".gz"
    suffix = (names[-2] if gz and len(names) > 1 else "") if gz else path.suffix.lower()
    if suffix not in suffixes:
        raise InputFileError(f"{path}: not a cell recording and not a python-can log "
                             f"({', '.join(suffixes)}, optionally .gz)")

    def _reader(p: Path) -> Iterable[Any]:
        with can.LogReader(p) as reader:
            yield from reader

    frames = frames or _reader
    if gz:
        read_bytes_check(path, f"{suffix[1:]}.gz CAN log")
    elif suffix in TEXT_LOG_SUFFIXES:
        first = check_text_file(path, f"{suffix[1:]} CAN log").strip()
        if suffix == ".csv":
            if first.replace(" ", "") != PYTHON_CAN_CSV_HEADER:
                raise InputFileError(
                    f"{path}: row 1: header {first[:80]!r} is neither a cell recording's "
                    f"(time_s,current_a,voltage_v,temperature_c) nor a python-can CSV log's ({PYTHON_CAN_CSV_HEADER})")
    else:
        read_bytes_check(path, f"{suffix[1:]} CAN log")
    n = 0
    latest = -math.inf
    error: InputFileError | None = None
    # A reader that fails half-way may leave an object whose __del__ raises again (asammdf's
    # MDF4 does), which Python would print as "Exception ignored in ..." at some later
    # collection: collect it here, with that report silenced, so the one line stays one.
    hook = sys.unraisablehook
    sys.unraisablehook = lambda _unraisable: None
    # Text readers log and skip lines they cannot parse: catch that instead of printing it.
    skipped = _Collect()
    can_log = logging.getLogger("can")
    can_log.addHandler(skipped)
    propagate, can_log.propagate = can_log.propagate, False
    try:
        try:
            for msg in frames(path):
                n += 1
                ts = float(msg.timestamp)
                if not math.isfinite(ts) or abs(ts) > MAX_LOG_TIMESTAMP_S:
                    error = InputFileError(f"{path}: frame {n}: timestamp {ts!r} is not a plausible time")
                    break
                if ts < latest - MAX_LOG_STEP_BACK_S:
                    error = InputFileError(
                        f"{path}: frame {n}: timestamp {ts:.6f} s is {latest - ts:.3g} s before an earlier frame's: "
                        "the log is out of order (logs joined end to end?); sort it by time or replay its parts apart")
                    break
                latest = max(latest, ts)
        except Exception as exc:  # noqa: BLE001 - python-can's readers raise many kinds on bad files
            where = f"frame {n + 1}" if n else "start"
            detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            if isinstance(exc, struct.error):  # a binary reader ran past the end of the file's bytes
                detail = f"the file ends inside a binary record, or is not this format ({detail})"
            error = InputFileError(f"{path}: cannot read as a {suffix[1:]} CAN log at {where}: {detail}")
    finally:
        gc.collect()
        sys.unraisablehook = hook
        can_log.removeHandler(skipped)
        can_log.propagate = propagate
    if error is not None:
        raise error
    if skipped.messages:
        raise InputFileError(f"{path}: not a valid {suffix[1:]} CAN log: {skipped.messages[0][:160]}")
    if n == 0:
        raise InputFileError(f"{path}: no CAN frames in this {suffix[1:]} log")
    return n


class _Collect(logging.Handler):
    """Keeps the warnings python-can's readers log about lines they skip."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage().splitlines()[0] if record.getMessage() else record.levelname)


def read_bytes_check(path: Path, what: str) -> None:
    """The file exists, is a file, and can be opened for reading."""
    if not path.exists():
        raise InputFileError(f"{path}: cannot read {what}: no such file")
    if not path.is_file():
        raise InputFileError(f"{path}: cannot read {what}: not a file")
    try:
        with path.open("rb") as fh:
            fh.read(1)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
