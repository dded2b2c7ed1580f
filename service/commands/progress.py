"""Progress bars with an ETA on stderr for the long commands (rich.progress).

``open_progress(enabled, description, total)`` returns a :class:`Bar` (``close()`` it when
done); ``progress_bar(...)`` is the same as a context manager.  A disabled bar (``--quiet``,
or stderr not a terminal without ``--progress``) does nothing, so callers never branch on it.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class Bar:
    """One task of a rich Progress (or nothing when disabled)."""

    def __init__(self, progress: Any | None, task: Any | None) -> None:
        self._progress = progress
        self._task = task

    @property
    def enabled(self) -> bool:
        return self._progress is not None

    def advance(self, n: float = 1, description: str | None = None) -> None:
        if self._progress is not None:
            kw = {"description": description} if description is not None else {}
            self._progress.update(self._task, advance=n, **kw)

    def update(self, completed: float | None = None, description: str | None = None,
               total: float | None = None) -> None:
        if self._progress is not None:
            kw: dict[str, Any] = {}
            if completed is not None:
                kw["completed"] = completed
            if description is not None:
                kw["description"] = description
            if total is not None:
                kw["total"] = total
            self._progress.update(self._task, **kw)

    def close(self) -> None:
        """Stop drawing (the last state stays on screen); safe to call twice."""
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def log(self, text: str) -> None:
        """A line above the bar (or nothing when disabled)."""
        if self._progress is not None:
            self._progress.console.print(text, markup=False, highlight=False)


def open_progress(enabled: bool, description: str, total: float | None, *, unit: str = "",
                  stream: Any = None) -> Bar:
    """A started bar with count, elapsed time and ETA (``total=None``: no ETA)."""
    if not enabled:
        return Bar(None, None)
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    stream = stream or sys.stderr
    # forced on a non-terminal (--progress into a log): still draw it
    isatty = getattr(stream, "isatty", lambda: False)()
    console = Console(file=stream, force_terminal=None if isatty else True)
    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn()]
    if unit:
        columns.append(TextColumn(unit))
    columns += [TextColumn("•"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
    # into a file or pipe (forced), redraw once a second rather than five times
    progress = Progress(*columns, console=console, transient=False, refresh_per_second=5 if isatty else 1)
    task = progress.add_task(description, total=total)
    progress.start()
    return Bar(progress, task)


@contextmanager
def progress_bar(enabled: bool, description: str, total: float | None, *, unit: str = "",
                 stream: Any = None) -> Iterator[Bar]:
    """:func:`open_progress` as a context manager (closed on the way out, also on errors)."""
    bar = open_progress(enabled, description, total, unit=unit, stream=stream)
    try:
        yield bar
    finally:
        bar.close()
