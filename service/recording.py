"""Cell recordings in the shared CSV format, read and validated.

Format: ``time_s,current_a,voltage_v,temperature_c`` with an optional ``soc_true``;
current positive = discharge (DESIGN §3). Every problem names the file and the row.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.errors import UserError

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

    def slice(self, start: int, stop: int | None = None) -> "Recording":
        sl = slice(start, stop)
        return Recording(
            self.path,
            self.time_s[sl],
            self.current_a[sl],
            self.voltage_v[sl],
            self.temperature_c[sl],
            None if self.soc_true is None else self.soc_true[sl],
        )


def _first_unparsable(path: Path, idx: list[int], cols: list[str]) -> str | None:
    """'row N: column C: ...' for the first value that is not a number (N = file line)."""
    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        next(reader, None)
        for line, row in enumerate(reader, start=2):
            for i, name in zip(idx, cols):
                cell = row[i] if i < len(row) else ""
                try:
                    float(cell)
                except ValueError:
                    return f"row {line}: column {name}: {cell!r} is not a number"
    return None


def save_recording(path: str | Path, columns: np.ndarray, fmt: str = "%.4f") -> Path:
    """Write ``[T, 4]`` columns time_s, current_a, voltage_v, temperature_c as the CSV
    :func:`load_recording` reads (simulated recordings: the validation grids, clean twins)."""
    path = Path(path)
    np.savetxt(path, columns, delimiter=",", header="time_s,current_a,voltage_v,temperature_c", comments="", fmt=fmt)
    return path


def load_recording(path: str | Path) -> Recording:
    """Read and validate a recording; raise :class:`UserError` naming file, row or column."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such recording file")
    try:
        with path.open(newline="") as fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read: {exc}") from exc
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise UserError(
            f"{path}: missing column(s) {', '.join(missing)}; header is {','.join(header) or '(empty)'}"
        )
    cols = list(REQUIRED_COLUMNS) + (["soc_true"] if "soc_true" in header else [])
    idx = [header.index(c) for c in cols]
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, usecols=idx, ndmin=2, dtype=float)
    except ValueError as exc:
        raise UserError(f"{path}: {_first_unparsable(path, idx, cols) or f'unparsable value: {exc}'}") from exc
    if data.shape[0] < 2:
        raise UserError(f"{path}: needs at least 2 data rows, has {data.shape[0]}")
    bad = ~np.isfinite(data)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise UserError(f"{path}: row {row + 2}: column {cols[col]} is not a finite number")
    t = data[:, 0]
    step = np.diff(t)
    if (step <= 0).any():
        k = int(np.argmax(step <= 0)) + 1
        raise UserError(
            f"{path}: row {k + 2}: time_s does not increase ({t[k - 1]:g} then {t[k]:g})"
        )
    return Recording(
        path=path,
        time_s=t,
        current_a=data[:, 1],
        voltage_v=data[:, 2],
        temperature_c=data[:, 3],
        soc_true=data[:, 4] if len(cols) == 5 else None,
    )
