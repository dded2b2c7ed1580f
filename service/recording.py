"""Cell recordings in the shared CSV format, read and validated.

Format: ``time_s,current_a,voltage_v,temperature_c`` with an optional ``soc_true``;
current positive = discharge (DESIGN §3). Every problem names the file and the row.
"""

from __future__ import annotations

import csv
import io
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.errors import UserError
from service.validation import (
    InputFileError,
    RecordingBounds,
    check_increasing,
    check_time_steps,
    check_values,
    header_text,
    read_text,
    separator_problem,
)

REQUIRED_COLUMNS = ("time_s", "current_a", "voltage_v", "temperature_c")


@dataclass(frozen=True)
class Recording:
    """One cell's time series (SI units, current positive = discharge)."""

    path: Path
    time_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray
    temperature_c: np.ndarray
    soc_true: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.path.stem

    def __len__(self) -> int:
        return int(self.time_s.size)

    def dt_s(self) -> np.ndarray:
        """Interval before each sample (first one 0): the estimator's actual step."""
        return np.diff(self.time_s, prepend=self.time_s[0])

    def slice(self, start: int, stop: int | None = None) -> Recording:
        sl = slice(start, stop)
        return Recording(
            self.path,
            self.time_s[sl],
            self.current_a[sl],
            self.voltage_v[sl],
            self.temperature_c[sl],
            None if self.soc_true is None else self.soc_true[sl],
        )


#: a number as the CSV reader (numpy.loadtxt) takes it: plain decimal or exponent, nan or inf;
#: Python's float() also takes digit separators ("4_1") and non-ASCII digits, which loadtxt refuses
PLAIN_NUMBER = re.compile(r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|nan|inf(?:inity)?)", re.IGNORECASE)


def _first_unparsable(path: Path, text: str, idx: list[int], cols: list[str]) -> str:
    """'row N: C: ...' for the first value that is not a plain number (N = file line), read the
    way the loader reads it: fields split at commas, nothing unquoted."""
    for line, raw in enumerate(text.splitlines()[1:], start=2):
        if not raw.strip():
            continue
        row = raw.split(",")
        for i, name in zip(idx, cols):
            cell = row[i].strip() if i < len(row) else ""
            if not PLAIN_NUMBER.fullmatch(cell):
                return (f"row {line}: {name}: {cell!r} is not a plain number (digits, '.', an exponent; "
                        "no quotes, digit separators or non-ASCII digits)")
    return "a row could not be read"


def save_recording(path: str | Path, columns: np.ndarray, fmt: str = "%.4f") -> Path:
    """Write ``[T, 4]`` columns time_s, current_a, voltage_v, temperature_c (``[T, 5]``: and
    soc_true) as the CSV :func:`load_recording` reads (simulated recordings: the validation grids,
    clean twins)."""
    path = Path(path)
    header = "time_s,current_a,voltage_v,temperature_c" + (",soc_true" if columns.shape[1] == 5 else "")
    np.savetxt(path, columns, delimiter=",", header=header, comments="", fmt=fmt)
    return path


def load_recording(path: str | Path, bounds: RecordingBounds | None = None) -> Recording:
    """Read and validate a recording; raise :class:`UserError` naming file, row and column.

    Text, header, numbers, finiteness, physical plausibility (``bounds``, default
    :data:`service.validation.DEFAULT_BOUNDS`) and increasing time are checked by
    :mod:`service.validation`.
    """
    path = Path(path)
    try:
        return _load(path, bounds)
    except InputFileError as exc:
        raise UserError(str(exc)) from None


def _load(path: Path, bounds: RecordingBounds | None) -> Recording:
    text = read_text(path, "recording")
    try:
        header = [h.strip() for h in next(csv.reader(io.StringIO(text, newline="")), [])]
    except csv.Error as exc:
        raise InputFileError(f"{path}: row 1: not a CSV header: {exc}") from None
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing and (why := separator_problem(header)) is not None:
        raise InputFileError(f"{path}: {why}")
    if missing:
        raise InputFileError(
            f"{path}: missing column(s) {', '.join(missing)}; header is {header_text(header)}"
        )
    cols = list(REQUIRED_COLUMNS) + (["soc_true"] if "soc_true" in header else [])
    twice = [c for c in cols if header.count(c) > 1]
    if twice:
        raise InputFileError(f"{path}: column {twice[0]} appears {header.count(twice[0])} times in the header; "
                             "which one to read is not clear")
    idx = [header.index(c) for c in cols]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy warns on a header-only file; counted below
            data = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1, usecols=idx, ndmin=2, dtype=float)
    except (ValueError, IndexError) as exc:
        raise InputFileError(f"{path}: {_first_unparsable(path, text, idx, cols)}") from exc
    if data.shape[0] < 2:
        raise InputFileError(f"{path}: needs at least 2 data rows, has {data.shape[0]}")
    check_values(path, {c: data[:, k] for k, c in enumerate(cols)}, bounds)
    t = data[:, 0]
    check_increasing(path, t)
    check_time_steps(path, t, data[:, 1])
    return Recording(
        path=path,
        time_s=t,
        current_a=data[:, 1],
        voltage_v=data[:, 2],
        temperature_c=data[:, 3],
        soc_true=data[:, 4] if len(cols) == 5 else None,
    )
