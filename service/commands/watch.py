"""``socd watch``: a live terminal table of a pack's cells from Zenoh (and optionally a PNG).

The view (rich.live + rich.table) is a summary header (pack SOC min/mean/max with their
cells, the pack line — usable SOC, remaining energy, imbalance, weakest cell —, current,
health flags and counters, latency) above a grid of cells that puts as many
``cell SOC σ V`` groups side by side as the terminal is wide, so a 96-cell pack fits one
screen.  Stale cells are yellow, cells whose filter was re-initialised (diverged) red;
``--sort soc|cell|sigma|voltage`` orders the grid (read down each column, then across).

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
from service.commands.common_args import (
    add_common_arguments,
    plot_file,
    positive_float,
    setup_logging,
)
from service.errors import MissingExtra

PLOT_EVERY_S = 2.0


def _endpoint(text: str) -> str:
    """A Zenoh endpoint as the service's config takes it (:func:`service.config.endpoint_problem`)."""
    from service.config import endpoint_problem

    if (problem := endpoint_problem(text)) is not None:
        raise argparse.ArgumentTypeError(problem)
    return text


def _key_chunk(text: str) -> str:
    """A key prefix or pack id as the service's config takes it (:func:`service.config.key_chunk_problem`)."""
    from service.config import key_chunk_problem

    if (problem := key_chunk_problem(text)) is not None:
        raise argparse.ArgumentTypeError(problem)
    return text
HISTORY = 3600
SORT_KEYS = ("cell", "soc", "sigma", "voltage")
#: characters one ``cell SOC σ V`` group takes in the grid (columns plus padding), and one
#: compact ``cell SOC`` group (used when the full grid would be taller than the terminal)
GROUP_WIDTH = 32
COMPACT_GROUP_WIDTH = 16
#: lines the header, the grid's column titles and its caption take
HEADER_LINES = 13


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "watch",
        help="live table of a pack's SOC from Zenoh",
        description="Show each cell's SOC, σ, voltage and flags as the service publishes them on Zenoh.",
    )
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", metavar="ENDPOINT", type=_endpoint,
                        help="Zenoh endpoint of the service (default tcp/127.0.0.1:7447)")
    parser.add_argument("--prefix", default="bms", type=_key_chunk, help="key prefix (default bms)")
    parser.add_argument("--pack", default="pack0", type=_key_chunk, help="pack id (default pack0)")
    parser.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE.json5",
                        help="a Zenoh JSON5 config (TLS, auth, ...); --connect applies where it sets no endpoints")
    parser.add_argument("--plot", type=plot_file, default=None, metavar="FILE.png",
                        help=f"keep a PNG of SOC over time up to date (every {PLOT_EVERY_S:g} s)")
    parser.add_argument("--once", action="store_true", help="print one table (from the snapshot) and exit")
    parser.add_argument("--timeout", type=positive_float, default=5.0, metavar="S",
                        help="--once: give up after S seconds without data (default 5)")
    parser.add_argument("--sort", choices=SORT_KEYS, default="cell",
                        help="order of the cells: index (default), SOC (lowest first), σ (largest first) or "
                             "voltage (lowest first)")
    add_common_arguments(parser)
    parser.set_defaults(func=_watch)


class PackView:
    """The latest state of a pack as seen on Zenoh (payload models, validated)."""

    def __init__(self) -> None:
        from service.daemon.payloads import CellParams, CellSoc, Health, Summary

        self.cells: dict[int, CellSoc] = {}
        #: the latest parameters and state of health of each cell (capacity, resistance growth)
        self.params: dict[int, CellParams] = {}
        self.summary: Summary | None = None
        self.health: Health | None = None
        self.messages = 0
        self.bad = 0
        self.history: deque[tuple[float, dict[int, float]]] = deque(maxlen=HISTORY)

    def on_sample(self, key: str, payload: str) -> None:
        from pydantic import ValidationError

        from service.daemon.payloads import CellParams, CellSoc, Health, Summary

        kind = key.rsplit("/", 1)[-1]
        self.messages += 1
        try:
            if kind == "soc":
                c = CellSoc.model_validate_json(payload)
                self.cells[c.cell] = c
            elif kind == "params":
                p = CellParams.model_validate_json(payload)
                self.params[p.cell] = p
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
        for p in snap.params:
            self.params.setdefault(p.cell, p)
        self.summary = self.summary or snap.summary
        self.health = self.health or snap.health

    def sorted_cells(self, key: str = "cell") -> list:
        """The cells in display order; cells without a value sort last."""
        from service.daemon.payloads import CellSoc

        def missing_last(x: float | None, sign: float = 1.0) -> tuple[bool, float]:
            return (x is None, 0.0 if x is None else sign * x)

        order = {
            "cell": lambda c: (False, float(c.cell)),
            "soc": lambda c: missing_last(c.soc_pct),
            "sigma": lambda c: missing_last(c.soc_std_pct, -1.0),
            "voltage": lambda c: missing_last(c.voltage_v),
        }[key]
        cells: list[CellSoc] = list(self.cells.values())
        return sorted(cells, key=lambda c: (order(c), c.cell))

    def state_of_health(self) -> str | None:
        """Capacity and resistance growth (% of the profile's) over the cells, lowest and highest
        capacity and highest resistance with their cells; None before any schema-2 params."""
        cap = {i: p for i, p in self.params.items() if p.capacity_pct is not None}
        res = {i: p for i, p in self.params.items() if p.resistance_pct is not None}
        if not cap and not res:
            return None
        parts = []
        if cap:
            lo = min(cap, key=lambda i: (cap[i].capacity_pct, i))
            hi = max(cap, key=lambda i: (cap[i].capacity_pct, -i))
            sd = cap[lo].capacity_std_ah / cap[lo].capacity_ah * 100 if cap[lo].capacity_std_ah and cap[lo].capacity_ah else None
            parts.append(f"capacity min {cap[lo].capacity_pct:.1f} %" + (f" ±{sd:.1f}" if sd is not None else "")
                         + f" (cell {lo})  max {cap[hi].capacity_pct:.1f} % (cell {hi})")
        if res:
            worst = max(res, key=lambda i: (res[i].resistance_pct, -i))
            parts.append(f"resistance max {res[worst].resistance_pct:.0f} % (cell {worst})")
        return "   ".join(parts) + "   (of the profile's)"

    def render(self, title: str, sort: str = "cell", width: int = 120, height: int | None = None):
        """The whole view as one rich renderable: summary header above the cell grid.

        With ``height`` (the terminal's), a grid that would not fit drops the σ and V
        columns to put more cells on each line.
        """
        from rich.console import Group

        compact = False
        if height is not None and self.cells:
            groups = max(1, width // GROUP_WIDTH)
            compact = HEADER_LINES + -(-len(self.cells) // groups) > height
        return Group(self.header(title), self.grid(sort, width, compact=compact))

    def header(self, title: str):
        from rich.table import Table
        from rich.text import Text

        t = Table.grid(padding=(0, 2))
        t.add_column(style="bold")
        t.add_column()
        t.title = title
        t.title_justify = "left"
        t.title_style = "bold"
        s = self.summary
        if s is not None:
            t.add_row("SOC", Text(
                f"min {_pct(s.soc_min_pct)} (cell {_opt(s.cell_min)})  mean {_pct(s.soc_mean_pct)}  "
                f"max {_pct(s.soc_max_pct)} (cell {_opt(s.cell_max)})  σ max {_pct(s.soc_std_max_pct)}"))
            t.add_row("usable", Text(pack_line(s)))
            t.add_row("pack", Text(
                f"{s.n_cells} cells   I {'-' if s.current_a is None else f'{s.current_a:.2f} A'}   "
                f"t {s.t_s:.1f} s"))
            raised = sorted(k for k, v in s.status_flags.items() if v)
            counts = Text(f"stale {s.n_stale}", style="yellow" if s.n_stale else "")
            counts.append(f"   diverged {sum(1 for c in self.cells.values() if c.resets)}",
                          style="red" if any(c.resets for c in self.cells.values()) else "")
            t.add_row("cells", counts)
            t.add_row("health", Text(", ".join(raised), style="bold red") if raised else Text("ok", style="green"))
        else:
            t.add_row("pack", Text("(no summary yet)", style="dim"))
        if self.health is not None:
            c, lat = self.health.counters, self.health.latency_ms
            t.add_row("counters", Text(
                f"frames in {c.get('frames_in', 0)}   rejected {c.get('frames_rejected', 0)} frames, "
                f"{c.get('values_rejected', 0)} values   "
                f"filter resets {c.get('filter_resets', 0)}   zenoh drops {c.get('zenoh_dropped', 0)}   "
                f"bus reconnects {c.get('bus_reconnects', 0)}"))
            t.add_row("latency", Text(
                f"estimate p50/p99 {_ms(lat.get('estimate_p50'))}/{_ms(lat.get('estimate_p99'))}   "
                f"publish p50/p99 {_ms(lat.get('publish_p50'))}/{_ms(lat.get('publish_p99'))}   "
                f"checkpoint: {self.health.checkpoint}"))
        soh = self.state_of_health()
        if soh is not None:
            t.add_row("SOH", Text(soh))
        t.add_row("watch", Text(f"{self.messages} messages, {self.bad} invalid", style="dim"))
        return t

    def grid(self, sort: str = "cell", width: int = 120, compact: bool = False):
        """Cells in side-by-side column groups sized to ``width``, read down then across."""
        from rich import box
        from rich.table import Table
        from rich.text import Text

        cells = self.sorted_cells(sort)
        groups = max(1, min(len(cells) or 1, width // (COMPACT_GROUP_WIDTH if compact else GROUP_WIDTH)))
        per_cell = 2 if compact else 4
        rows = -(-len(cells) // groups) if cells else 0
        t = Table(box=box.SIMPLE_HEAD, padding=(0, 1), pad_edge=False, show_edge=False,
                  caption=f"sorted by {sort}, read down then across; ~ stale, ! filter re-initialised"
                + ("; σ and V hidden to fit the screen" if compact else ""),
                  caption_justify="left")
        for _ in range(groups):
            t.add_column("cell", justify="right", style="bold", min_width=4, no_wrap=True)
            t.add_column("SOC %", justify="right", min_width=6, no_wrap=True)
            if not compact:
                t.add_column("σ %", justify="right", min_width=5, no_wrap=True)
                t.add_column("V", justify="right", min_width=6, no_wrap=True)
        for r in range(rows):
            row: list = []
            for g in range(groups):
                k = g * rows + r
                if k < len(cells):
                    c = cells[k]
                    style = "red" if c.resets else ("yellow" if c.stale else "")
                    mark = "!" if c.resets else ("~" if c.stale else " ")
                    row += [Text(f"{c.cell}{mark}", style=style or "bold"), Text(_num(c.soc_pct, 2), style)]
                    if not compact:
                        row += [Text(_num(c.soc_std_pct, 2), style), Text(_num(c.voltage_v, 3), style)]
                else:
                    row += [""] * per_cell
            t.add_row(*row)
        if not cells:
            t.add_row(Text("(no cells yet)", style="dim"), *[""] * (per_cell * groups - 1))
        return t


def pack_line(s: Any) -> str:
    """The summary's pack view on one line (``-`` where the daemon sent none)."""
    if s.usable_soc_pct is None and s.remaining_energy_wh is None:
        return "-"
    energy = "-" if s.remaining_energy_wh is None else f"{s.remaining_energy_wh:,.0f} Wh"
    usable_e = "-" if s.usable_energy_wh is None else f"{s.usable_energy_wh:,.0f}"
    return (f"SOC {_pct(s.usable_soc_pct)}  discharge {_ah(s.usable_discharge_ah)} / charge "
            f"{_ah(s.usable_charge_ah)}  energy {energy} (usable {usable_e})  imbalance "
            f"{_ah(s.imbalance_ah)}  weakest {_opt(s.weakest_cell)}")


def _ah(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f} Ah"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f} %"


def _opt(x: int | None) -> str:
    return "-" if x is None else str(x)


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f} ms"


def _num(x: float | None, nd: int) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


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
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)  # a viewer never sees a half-written PNG


async def watch(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    import zenoh
    from rich.console import Console

    from service.daemon.payloads import keys
    from service.daemon.zenoh_pub import ZenohConfigError

    k = keys(args.prefix, args.pack)
    loop = asyncio.get_running_loop()
    view = PackView()
    console = Console(file=out)
    try:
        session = zenoh.open(_session_config(args))
    except ZenohConfigError as exc:
        raise UserError(str(exc).replace("zenoh.config_file", "--zenoh-config", 1)) from None
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
            console.print(view.render(title, args.sort, console.width, console.height if console.is_terminal else None))
            if args.plot:
                write_plot(args.plot, view, title)
            return 0
        await _live(console, view, title, args)
        return 0
    finally:
        for s in subs:
            s.undeclare()
        session.close()


def _session_config(args: argparse.Namespace):
    """A peer that listens nowhere, connects to ``--connect``, no multicast; under ``--zenoh-config``."""
    from service.daemon.zenoh_pub import config_from_section

    section = argparse.Namespace(mode="peer", listen=[], connect=[args.connect], scouting_multicast=False,
                                 config_file=getattr(args, "zenoh_config", None))
    return config_from_section(section)


async def _live(console: Any, view: PackView, title: str, args: argparse.Namespace) -> None:
    """Redraw in place on a terminal (rich.live); print a fresh table every 2 s otherwise."""
    from rich.live import Live

    last_plot = 0.0

    async def plot_now() -> None:
        nonlocal last_plot
        if args.plot and time.monotonic() - last_plot > PLOT_EVERY_S:
            last_plot = time.monotonic()
            await asyncio.to_thread(write_plot, args.plot, view, title)

    if not console.is_terminal:
        while True:
            console.print(view.render(title, args.sort, console.width))
            await plot_now()
            await asyncio.sleep(2.0)
    with Live(view.render(title, args.sort, console.width, console.height), console=console, auto_refresh=False,
              screen=True, vertical_overflow="crop") as live:
        while True:
            live.update(view.render(title, args.sort, console.width, console.height), refresh=True)
            await plot_now()
            await asyncio.sleep(0.5)


def _watch(args: argparse.Namespace) -> int:
    from service.extras import install_hint, installed

    setup_logging(args)
    if args.plot and not installed("matplotlib"):
        # said now, not when the first data arrives (or never, where the service is not up)
        raise MissingExtra(f"--plot {install_hint('matplotlib')}")
    try:
        return asyncio.run(watch(args))
    except KeyboardInterrupt:
        return 0
