"""Opening the daemon's CAN bus at start-up with a limit on failed attempts.

:class:`~service.daemon.can_rx.CanReceiver` retries a failing open with backoff; a bus that
never opens (wrong channel, interface down, driver missing) would keep ``socd run`` retrying
for ever while it looks alive.  :class:`BusOpener` counts failures until the bus first opens
and, after ``bus.max_open_retries`` retries, raises :class:`BusUnavailable`, which the
receiver does not catch: the daemon stops and ``socd run`` exits 1 naming the interface and
channel.  Once the bus has opened, a link that goes down later is reopened for as long as it
takes (the estimate is kept and resumes when the link returns; deploy/socd.service relies on
it).  ``max_open_retries = 0`` retries for ever at start-up too.
"""

from __future__ import annotations

from typing import Any

import can


class BusUnavailable(RuntimeError):
    """The bus could not be opened ``max_open_retries + 1`` times in a row."""


class BusOpener:
    """``can.Bus(**bus.bus_kwargs())`` as a factory that gives up after too many failures."""

    def __init__(self, bus: Any) -> None:
        self.bus = bus
        self.kwargs = bus.bus_kwargs()
        self.max_retries = int(getattr(bus, "max_open_retries", 0))
        self.failures = 0
        self.opened_once = False

    def __call__(self) -> can.BusABC:
        try:
            opened = can.Bus(**self.kwargs)
        except Exception as exc:
            self.failures += 1
            if self.max_retries and not self.opened_once and self.failures > self.max_retries:
                raise BusUnavailable(
                    f"cannot open CAN bus {self.bus.interface}:{self.bus.channel} after {self.failures} "
                    f"attempts ({exc}); giving up (bus.max_open_retries = {self.max_retries}, "
                    f"--max-bus-retries 0 retries for ever)") from exc
            if isinstance(exc, (can.CanError, OSError, ValueError)):
                raise
            # a backend's own kind (a missing vendor library raises NameError, a socketcand bus without
            # host and port TypeError) is a failed open like the others, counted and retried
            raise can.CanInitializationError(f"{type(exc).__name__}: {exc}") from exc
        self.failures = 0
        self.opened_once = True
        return opened
