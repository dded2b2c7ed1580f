"""python-can receive path for asyncio that never loses an error, with reconnect and backoff.

``can.Notifier(bus, [can.AsyncBufferedReader()], loop=loop)`` is python-can's asyncio path,
but in 4.6 its errors can vanish (open upstream bugs):

- thread-backed buses (``virtual``, ``remote``, most vendor drivers): a listener exception
  raised in the loop callback bypasses ``_rx_thread``'s handler (hardbyte/python-can#1912);
  a receive error calls ``on_error`` and then kills the thread, leaving the coroutine that
  awaits the reader stuck forever (#907, #1865);
- fd-backed buses (SocketCAN): an exception from ``bus.recv(0)`` in the loop's reader
  callback reaches no listener at all, and the reader keeps firing (#1865).

:class:`GuardedNotifier` closes those holes: every receive error and every listener
exception is routed to a callback, counted and logged.  :class:`CanReceiver` turns a
receive error (``CanError``/``OSError``: bus-off, interface down, a remote server gone)
into close → wait → reopen with exponential backoff between ``bus.reconnect_initial_s``
and ``bus.reconnect_max_s``, counting every step.
"""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Callable
from typing import Any

import can

from service.daemon.health import HealthMonitor

log = logging.getLogger(__name__)

#: SocketCAN error-frame class bit for bus-off (linux/can/error.h CAN_ERR_BUSOFF)
CAN_ERR_BUSOFF = 0x40
#: frames read per readiness callback on fd-backed buses
FD_DRAIN_MAX = 256
#: frames handed to the loop in one call by the receive thread of thread-backed buses
RX_BATCH_MAX = 256
#: most frames taken from an owned bus's queue before it is shut down for a reconnect
DRAIN_MAX = 100_000


class ReceiverClosed(Exception):
    """:meth:`CanReceiver.recv` was called after (or while) the receiver was closed."""


class _ReceiveError:
    """Marker put in the reader's queue so the consumer sees the error in order."""

    __slots__ = ("exc",)

    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


class GuardedNotifier(can.Notifier):
    """A :class:`can.Notifier` (loop mode) whose errors always reach a callback.

    ``on_receive_error(exc)`` is called on the loop once per failed receive; the reader for
    that bus is then stopped (a failed bus needs a new Bus object, which is the caller's
    job).  ``on_listener_error(exc)`` is called on the loop for an exception raised by a
    listener; delivery continues with the next message.  Frames read before :meth:`stop`
    but dispatched after it are still delivered (python-can's own Notifier drops them).
    """

    def __init__(
        self,
        bus: can.BusABC,
        listeners: list[Any],
        *,
        loop: asyncio.AbstractEventLoop,
        on_receive_error: Callable[[BaseException], None],
        on_listener_error: Callable[[BaseException], None],
        timeout: float = 0.5,
    ) -> None:
        self._on_receive_error_cb = on_receive_error
        self._on_listener_error_cb = on_listener_error
        super().__init__(bus, listeners, timeout=timeout, loop=loop)

    # thread-backed buses --------------------------------------------------------------
    def _rx_thread(self, bus: can.BusABC) -> None:
        loop = self._loop
        assert loop is not None
        # Messages already waiting go to the loop in one batch: one wake-up of the loop (and
        # one GIL hand-over) per batch instead of per frame.
        deliver = functools.partial(loop.call_soon_threadsafe, self._dispatch_batch)
        while not self._stopped:
            batch: list[can.Message] = []
            try:
                msg = bus.recv(self.timeout)
                while msg is not None:
                    batch.append(msg)
                    if len(batch) >= RX_BATCH_MAX:
                        break
                    msg = bus.recv(0)
            except Exception as exc:  # noqa: BLE001 - every receive error is reported
                self.exception = exc
                if batch:
                    self._call_on_loop(self._dispatch_batch, batch)
                if not self._stopped:
                    self._call_on_loop(self._receive_failed, exc)
                return
            if batch:
                try:
                    deliver(batch)
                except RuntimeError:  # loop closed under us: shutting down
                    return

    def _call_on_loop(self, fn: Callable[..., None], *args: Any) -> None:
        try:
            self._loop.call_soon_threadsafe(fn, *args)  # type: ignore[union-attr]
        except RuntimeError:
            pass

    # fd-backed buses (SocketCAN) --------------------------------------------------------
    def _on_message_available(self, bus: can.BusABC) -> None:
        # Drain what is ready (bounded, so one busy bus cannot starve the loop).
        for _ in range(FD_DRAIN_MAX):
            try:
                msg = bus.recv(0)
            except Exception as exc:  # noqa: BLE001
                self.exception = exc
                try:
                    self._loop.remove_reader(bus.fileno())  # type: ignore[union-attr]
                except Exception:  # noqa: BLE001 - fd may already be gone
                    pass
                self._receive_failed(exc)
                return
            if msg is None:
                return
            self._dispatch(msg)

    # common --------------------------------------------------------------------------
    def _dispatch_batch(self, batch: list[can.Message]) -> None:
        for msg in batch:
            self._dispatch(msg)

    def _dispatch(self, msg: can.Message) -> None:
        # Deliver even after stop(): a batch the receive thread (or the fd callback) read
        # before the stop is still queued on the loop, and the frames in it came off the bus.
        # The listeners outlive this notifier (see :class:`_Reader`), so nothing is lost.
        try:
            self._on_message_received(msg)
        except Exception as exc:  # noqa: BLE001 - a listener bug must not stop reception
            self._on_listener_error_cb(exc)

    def _receive_failed(self, exc: BaseException) -> None:
        if not self._stopped:
            self._on_receive_error_cb(exc)


class _Reader(can.AsyncBufferedReader):
    """AsyncBufferedReader whose ``on_error`` wakes the consumer instead of hanging it.

    One reader lives as long as the :class:`CanReceiver`, across reconnects, so frames
    already received when a bus fails are still delivered; ``stop()`` (called by every
    Notifier that stops) therefore does nothing.
    """

    def on_error(self, exc: Exception) -> None:
        self.buffer.put_nowait(_ReceiveError(exc))  # type: ignore[arg-type]

    def stop(self) -> None:
        pass


class CanReceiver:
    """Messages from a CAN bus as an async iterator, surviving bus errors.

    Either ``open_bus`` (a factory: the receiver owns and re-creates the Bus) or ``bus``
    (given by the caller, who owns it: on an error the receiver waits and re-attaches to
    the same object, and never shuts it down) must be set.
    """

    def __init__(
        self,
        health: HealthMonitor,
        *,
        open_bus: Callable[[], can.BusABC] | None = None,
        bus: can.BusABC | None = None,
        reconnect_initial_s: float = 0.1,
        reconnect_max_s: float = 10.0,
    ) -> None:
        if (open_bus is None) == (bus is None):
            raise ValueError("give exactly one of open_bus and bus")
        self.health = health
        self._open_bus = open_bus
        self._given_bus = bus
        self.bus: can.BusABC | None = None
        self._notifier: GuardedNotifier | None = None
        self._reader: _Reader | None = None
        self._reader_obj = _Reader()
        self._initial = max(1e-3, reconnect_initial_s)
        self._max = max(self._initial, reconnect_max_s)
        self._delay = self._initial
        self._closed = False
        self._healthy = False  # a message arrived since the last (re)connect
        self.connected = asyncio.Event()

    # -- connection -------------------------------------------------------------------
    async def _connect(self) -> None:
        loop = asyncio.get_running_loop()
        while not self._closed:
            try:
                if self._given_bus is not None:
                    bus = self._given_bus
                else:
                    assert self._open_bus is not None
                    bus = await loop.run_in_executor(None, self._open_bus)
                reader = self._reader_obj
                notifier = GuardedNotifier(
                    bus,
                    [reader],
                    loop=loop,
                    on_receive_error=reader.on_error,
                    on_listener_error=self._listener_error,
                )
            except (can.CanError, OSError, ValueError) as exc:
                self.health.count("bus_open_failures", flag="bus_error")
                log.warning("cannot open CAN bus (%s); retrying in %.2f s", exc, self._delay)
                await self._backoff()
                continue
            self.bus, self._reader, self._notifier = bus, reader, notifier
            self._healthy = False
            self.connected.set()
            return

    async def _backoff(self) -> None:
        await asyncio.sleep(self._delay)
        self._delay = min(self._max, self._delay * 2)

    def _listener_error(self, exc: BaseException) -> None:
        self.health.count("listener_errors")
        log.error("CAN listener raised %r; message dropped", exc)

    def _teardown(self) -> None:
        self.connected.clear()
        notifier, bus = self._notifier, self.bus
        self._notifier = self._reader = None
        self.bus = None
        if notifier is not None:
            try:
                notifier.stop(timeout=1.0)
            except Exception as exc:  # noqa: BLE001
                log.debug("notifier stop: %r", exc)
        if bus is not None and self._given_bus is None:
            self._drain(bus)
            try:
                bus.shutdown()
            except Exception as exc:  # noqa: BLE001 - a dead bus may fail to close
                log.debug("bus shutdown: %r", exc)
                # python-can would retry (and raise again) from BusABC.__del__
                bus._is_shutdown = True  # type: ignore[attr-defined]

    def _drain(self, bus: can.BusABC) -> None:
        """Hand on what an owned bus still holds before it is shut down (a bus-off leaves the
        frames received before it in the driver's queue; shutdown would discard them)."""
        n = 0
        for _ in range(DRAIN_MAX):
            try:
                msg = bus.recv(0)
            except Exception:  # noqa: BLE001 - a failed bus may fail again; nothing more to get
                break
            if msg is None:
                break
            self._reader_obj.on_message_received(msg)
            n += 1
        self.health.count("frames_drained_at_reconnect", n)

    async def _reconnect(self, why: str) -> None:
        self.health.count("bus_reconnects", flag="bus_error")
        log.warning("CAN bus failed (%s): reconnecting in %.2f s", why, self._delay)
        self._teardown()
        await self._backoff()
        await self._connect()

    # -- the public path ----------------------------------------------------------------
    async def recv(self) -> can.Message:
        """The next frame the bus delivered; receive errors are counted and reconnected, never raised.

        Error frames are returned too (after a bus-off one has triggered a reconnect), so
        the consumer can count every frame that arrived exactly once.
        """
        while True:
            if self._reader is None:
                await self._connect()
                if self._reader is None:  # closed while connecting
                    raise ReceiverClosed("CAN receiver closed")
            item = await self._reader.get_message()
            if isinstance(item, _ReceiveError):
                self.health.count("bus_errors", flag="bus_error")
                await self._reconnect(repr(item.exc))
                continue
            if item.is_error_frame:
                self.health.raise_flag("bus_error")
                if item.arbitration_id & CAN_ERR_BUSOFF:
                    self.health.count("bus_off", flag="bus_error")
                    await self._reconnect("bus-off")
                return item
            if not self._healthy:
                self._healthy = True
                self._delay = self._initial
            return item

    def __aiter__(self) -> CanReceiver:
        return self

    async def __anext__(self) -> can.Message:
        return await self.recv()

    def backlog(self) -> int:
        """Messages received but not yet consumed."""
        return self._reader_obj.buffer.qsize()

    def send(self, msg: can.Message) -> bool:
        """Send without ever blocking the loop (timeout=0); count and swallow failures."""
        bus = self.bus
        if bus is None:
            self.health.count("can_send_skipped", flag="publish_drops")
            return False
        try:
            bus.send(msg, timeout=0)
        except (can.CanError, OSError, ValueError) as exc:
            self.health.count("can_send_failed", flag="publish_drops")
            log.debug("CAN send failed: %r", exc)
            return False
        return True

    async def start(self) -> None:
        await self._connect()

    def close(self) -> None:
        self._closed = True
        self._teardown()
        # frames received but never consumed (the service is stopping): counted, not silently gone
        left = sum(1 for item in list(self._reader_obj.buffer._queue)  # type: ignore[attr-defined]
                   if not isinstance(item, _ReceiveError))
        self.health.count("frames_unprocessed_at_stop", left)
