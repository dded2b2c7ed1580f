"""A running daemon on python-can's in-process ``virtual`` bus, fed a list of frames.

The in-process replay is the reference a replay over another bus is compared with: the
``virtual`` bus opened with ``preserve_timestamps=True`` hands the receiver the sender's
stamps unchanged.  Reuse in a test module::

    from daemon_support import run_daemon

    d = run_daemon(config, frames)        # config.bus.channel names the virtual channel
    d.estimator.soc
"""

from __future__ import annotations

import asyncio
import time

import can

from replay.player import play
from service.cell.profile import load_profile
from service.daemon.daemon import Daemon


def run_daemon(config, frames: list[can.Message], timeout_s: float = 120.0) -> Daemon:
    """Run a :class:`Daemon` on ``config.bus.channel``, send ``frames`` unpaced with their stamps
    kept, wait until it has taken every one of them in, stop it cleanly and return it."""

    async def main() -> Daemon:
        bus = can.Bus(interface="virtual", channel=config.bus.channel)
        tx = can.Bus(interface="virtual", channel=config.bus.channel, preserve_timestamps=True)
        try:
            d = Daemon(config, bus, profile=load_profile(config.cell_profile), install_signal_handlers=False)
            stop = asyncio.Event()
            task = asyncio.create_task(d.run(stop))
            await d.wait_started()
            await asyncio.wait_for(d.receiver.connected.wait(), 10)
            stats = await asyncio.to_thread(play, tx, frames, 0.0)
            assert stats.frames_sent == len(frames), stats
            end = time.monotonic() + timeout_s
            while d.decoder.counters["frames_in"] < len(frames) and time.monotonic() < end:
                await asyncio.sleep(0.02)
            stop.set()
            await asyncio.wait_for(task, 30)
        finally:
            tx.shutdown()
            bus.shutdown()
        assert d.decoder.counters["frames_in"] == len(frames), "the daemon did not take in every frame"
        return d

    return asyncio.run(main())
