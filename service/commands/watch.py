"""``socd watch``: a live terminal table of a pack's cells from Zenoh (and optionally a PNG).

Subscribes to ``<prefix>/<pack>/cell/*/soc``, ``.../summary`` and ``.../health``; joins late
by asking the ``<prefix>/<pack>/snapshot`` queryable for every cell's latest state first.
Zenoh's callbacks run on Zenoh's threads and are handed to the asyncio loop with
``loop.call_soon_threadsafe``; the blocking ``get`` runs in a worker thread.

The session is a peer that listens nowhere (``listen`` set explicitly to nothing) and
connects to ``--connect``; multicast scouting is off.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any, TextIO

from service.cli import UserError

PLOT_EVERY_S = 2.0
HISTORY = 3600


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "watch",
        help="live table of a pack's SOC from Zenoh",
        description="Show each cell's SOC, σ, voltage and flags as the service publishes them on Zenoh.",
    )
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", metavar="ENDPOINT",
                        help="Zenoh endpoint of the service (default tcp/127.0.0.1:7447)")
    parser.add_argument("--prefix", default="bms", help="key prefix (default bms)")
    parser.add_argument("--pack", default="pack0", help="pack id (default pack0)")
    parser.add_argument("--plot", type=Path, default=None, metavar="FILE.png",
                        help=f"keep a PNG of SOC over time up to date (every {PLOT_EVERY_S:g} s)")
    parser.add_argument("--once", action="store_true", help="print one table (from the snapshot) and exit")
    parser.add_argument("--timeout", type=float, default=5.0, metavar="S",
                        help="--once: give up after S seconds without data (default 5)")
    parser.set_defaults(func=_watch)


class PackView:
    """The latest state of a pack as seen on Zenoh (payload models, validated)."""

    def __init__(self) -> None:
        from service.daemon.payloads import CellSoc, Health, Summary

        self.cells: dict[int, CellSoc] = {}
        self.summary: Summary | None = None
        self.health: Health | None = None
        self.messages = 0
        self.bad = 0
        self.history: deque[tuple[float, dict[int, float]]] = deque(maxlen=HISTORY)

    def on_sample(self, key: str, payload: str) -> None:
        from pydantic import ValidationError

        from service.daemon.payloads import CellSoc, Health, Summary

        kind = key.rsplit("/", 1)[-1]
        self.messages += 1
        try:
            if kind == "soc":
                c = CellSoc.model_validate_json(payload)
                self.cells[c.cell] = c
            elif kind == "summary":
                self.summary = Summary.model_validate_json(payload)
                self.history.append((self.summary.t_s, {i: c.soc_pct for i, c in self.cells.items()
                                                        if c.soc_pct is not None}))
            elif kind == "health":
                self.health = Health.model_validate_json(payload)
        except ValidationError:
            self.bad += 1

    def on_snapshot(self, payload: str) -> None:
        from service.daemon.payloads import Snapshot

        snap = Snapshot.model_validate_json(payload)
        for c in snap.cells:
            self.cells.setdefault(c.cell, c)
        self.summary = self.summary or snap.summary
        self.health = self.health or snap.health

    def table(self, title: str) -> str:
        s = self.summary
        lines = [title]
        if s is not None:
            flags = [k for k, v in s.status_flags.items() if v]
            lines.append(
                f"t={s.t_s:.1f} s  cells {s.n_cells}  SOC mean {_pct(s.soc_mean_pct)}  "
                f"min {_pct(s.soc_min_pct)} (cell {s.cell_min})  max {_pct(s.soc_max_pct)} (cell {s.cell_max})  "
                f"I {'-' if s.current_a is None else f'{s.current_a:.2f} A'}  stale {s.n_stale}"
            )
            lines.append("flags: " + (", ".join(sorted(flags)) if flags else "none"))
        if self.health is not None:
            c, lat = self.health.counters, self.health.latency_ms
            lines.append(
                f"frames in {c.get('frames_in', 0)}  rejected {c.get('frames_rejected', 0)}  "
                f"resets {c.get('filter_resets', 0)}  zenoh drops {c.get('zenoh_dropped', 0)}  "
                f"latency p50/p99 {lat.get('publish_p50')}/{lat.get('publish_p99')} ms"
            )
        lines.append(f"{'cell':>5} {'SOC %':>7} {'σ %':>6} {'V':>7}  flags")
        for i in sorted(self.cells):
            c = self.cells[i]
            flags = []
            if c.stale:
                flags.append("STALE")
            if c.resets:
                flags.append(f"resets={c.resets}")
            lines.append(f"{i:>5} {_num(c.soc_pct, 7, 2)} {_num(c.soc_std_pct, 6, 2)} {_num(c.voltage_v, 7, 3)}  "
                         + " ".join(flags))
        if not self.cells:
            lines.append("  (no cells yet)")
        return "\n".join(lines)


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f} %"


def _num(x: float | None, width: int, nd: int) -> str:
    return f"{'-':>{width}}" if x is None else f"{x:>{width}.{nd}f}"


def write_plot(path: Path, view: PackView, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5))
    if view.history:
        t = [h[0] for h in view.history]
        cells = sorted({i for _, d in view.history for i in d})
        for i in cells:
            ax.plot(t, [d.get(i, float("nan")) for _, d in view.history], lw=0.8)
    ax.set_xlabel("frame time, s")
    ax.set_ylabel("SOC, %")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)  # a viewer never sees a half-written PNG


async def watch(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    import zenoh

    from service.daemon.payloads import keys
    from service.daemon.zenoh_pub import zenoh_config

    k = keys(args.prefix, args.pack)
    loop = asyncio.get_running_loop()
    view = PackView()
    try:
        session = zenoh.open(zenoh_config("peer", [], [args.connect], False))
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError
        raise UserError(f"cannot open a Zenoh session to {args.connect}: {exc}") from None

    def bridge(sample: Any) -> None:  # Zenoh thread -> loop
        loop.call_soon_threadsafe(view.on_sample, str(sample.key_expr), sample.payload.to_string())

    subs = []
    try:
        if not args.once:
            subs = [session.declare_subscriber(f"{k.base}/cell/*/soc", bridge),
                    session.declare_subscriber(k.summary, bridge),
                    session.declare_subscriber(k.health, bridge)]

        def query() -> str | None:
            for reply in session.get(k.snapshot, timeout=2.0):
                if reply.ok is not None:
                    return reply.ok.payload.to_string()
            return None

        end = time.monotonic() + args.timeout
        snap = None
        while snap is None and time.monotonic() < end:
            snap = await asyncio.to_thread(query)  # the connection may still be coming up
            if snap is None:
                await asyncio.sleep(0.2)
        if snap is not None:
            view.on_snapshot(snap)
        title = f"socd watch {k.base} via {args.connect}"
        if args.once:
            if snap is None:
                print(f"socd watch: no snapshot from {k.snapshot} within {args.timeout:g} s", file=sys.stderr)
                return 1
            print(view.table(title), file=out)
            if args.plot:
                write_plot(args.plot, view, title)
            return 0
        tty = out.isatty()
        last_plot = 0.0
        while True:
            text = view.table(title + f"  ({view.messages} messages)")
            out.write(("\x1b[H\x1b[2J" + text + "\n") if tty else (text + "\n\n"))
            out.flush()
            if args.plot and time.monotonic() - last_plot > PLOT_EVERY_S:
                last_plot = time.monotonic()
                await asyncio.to_thread(write_plot, args.plot, view, title)
            await asyncio.sleep(0.5 if tty else 2.0)
    finally:
        for s in subs:
            s.undeclare()
        session.close()


def _watch(args: argparse.Namespace) -> int:
    try:
        return asyncio.run(watch(args))
    except KeyboardInterrupt:
        return 0
