"""``socd watch``: the rich view of a 96-cell pack (header, sort orders, colours, width), and
``--once`` against a real Zenoh publisher on 127.0.0.1."""

from __future__ import annotations

import argparse
import asyncio
import io
import re
import socket

import numpy as np
import pytest
from rich.console import Console

from replay.pack import FrameBuilder
from service.bus.decoder import FrameDecoder
from service.cell.ocv import OcvTable
from service.commands.watch import PackView, watch
from service.config import build_config
from service.daemon.health import HealthMonitor
from service.daemon.payloads import CellSoc, Health, Summary
from service.daemon.zenoh_pub import PublishRound, ZenohPublisher
from service.estimators.pack_view import OcvEnergy, pack_view

N = 96
STALE, DIVERGED = 5, 7


def _view() -> PackView:
    rng = np.random.default_rng(3)
    v = PackView()
    soc = rng.uniform(60.0, 90.0, N).round(2)
    for i in range(N):
        v.cells[i] = CellSoc(pack="p", t_s=10.0, cell=i, soc_pct=float(soc[i]), soc_std_pct=round(0.3 + 0.01 * i, 2),
                             voltage_v=round(3.5 + 0.005 * i, 3), stale=i == STALE, resets=1 if i == DIVERGED else 0)
    lo, hi = int(np.argmin(soc)), int(np.argmax(soc))
    v.summary = Summary(pack="p", t_s=10.0, n_cells=N, soc_mean_pct=round(float(soc.mean()), 2),
                        soc_min_pct=float(soc[lo]), soc_max_pct=float(soc[hi]), cell_min=lo, cell_max=hi,
                        soc_std_max_pct=1.25, current_a=12.5, n_stale=1,
                        status_flags={"stale_cells": True, "diverged": True, "zenoh_down": False},
                        usable_soc_pct=61.5, usable_discharge_ah=1.725, usable_charge_ah=1.08,
                        remaining_energy_wh=812.4, usable_energy_wh=655.0, imbalance_ah=0.6, weakest_cell=lo,
                        fullest_cell=hi)
    v.health = Health(pack="p", t_s=10.0, uptime_s=60.0, status_flags={}, checkpoint="restored",
                      counters={"frames_in": 1234, "frames_rejected": 2, "filter_resets": 1},
                      latency_ms={"estimate_p50": 0.4, "estimate_p99": 1.2, "publish_p50": 2.0, "publish_p99": 4.5})
    return v


def _render(v: PackView, sort: str, width: int = 120, height: int | None = None) -> str:
    c = Console(record=True, width=width, file=io.StringIO())
    c.print(v.render("socd watch bms/p", sort, width, height))
    return c.export_text()


def _cells_in_order(text: str, per_cell: int = 4) -> list[int]:
    """Cell indices of the grid, read down each column group, then across."""
    rows = []
    for line in text.splitlines():
        tokens = line.split()
        if tokens and re.fullmatch(r"\d+[~!]?", tokens[0]) and len(tokens) % per_cell == 0 and len(tokens) >= per_cell:
            rows.append([int(tokens[k].rstrip("~!")) for k in range(0, len(tokens), per_cell)])
    groups = max(len(r) for r in rows)
    return [r[g] for g in range(groups) for r in rows if g < len(r)]


def test_header_and_every_cell_on_one_120_column_screen() -> None:
    v = _view()
    text = _render(v, "cell", 120)
    lines = text.splitlines()
    assert lines[0].startswith("socd watch bms/p")
    s = v.summary
    assert f"min {s.soc_min_pct:.2f} % (cell {s.cell_min})" in text and f"mean {s.soc_mean_pct:.2f} %" in text
    assert f"max {s.soc_max_pct:.2f} % (cell {s.cell_max})" in text
    assert "stale 1" in text and "diverged 1" in text and "diverged, stale_cells" in text
    assert (f"usable    SOC 61.50 %  discharge 1.725 Ah / charge 1.080 Ah  energy 812 Wh (usable 655)  "
            f"imbalance 0.600 Ah  weakest {s.weakest_cell}") in text
    assert "frames in 1234" in text and "estimate p50/p99 0.4 ms/1.2 ms" in text
    assert max(len(line) for line in lines) <= 120
    assert len(lines) <= 45  # 96 cells in three groups of 32 rows plus the header
    assert _cells_in_order(text) == list(range(N))
    assert f"{STALE}~" in text and f"{DIVERGED}!" in text


@pytest.mark.parametrize(("sort", "key", "reverse"), [("soc", "soc_pct", False), ("sigma", "soc_std_pct", True),
                                                      ("voltage", "voltage_v", False)])
def test_sort_orders(sort: str, key: str, reverse: bool) -> None:
    v = _view()
    order = _cells_in_order(_render(v, sort, 120))
    values = [getattr(v.cells[i], key) for i in order]
    assert sorted(order) == list(range(N))
    assert values == sorted(values, reverse=reverse)


def test_small_terminal_drops_sigma_and_voltage_to_fit() -> None:
    v = _view()
    text = _render(v, "soc", 80, height=40)
    assert "σ and V hidden to fit the screen" in " ".join(text.split())
    order = _cells_in_order(text, per_cell=2)
    assert sorted(order) == list(range(N))
    assert len(text.splitlines()) <= 40 and max(len(line) for line in text.splitlines()) <= 80


def test_stale_and_diverged_cells_are_coloured() -> None:
    v = _view()
    c = Console(record=True, width=120, file=io.StringIO(), force_terminal=True, color_system="standard")
    c.print(v.grid("cell", 120))
    ansi = c.export_text(styles=True)
    assert re.search(rf"\x1b\[(1;)?33m\s*{STALE}~", ansi), "stale cell not yellow"
    assert re.search(rf"\x1b\[(1;)?31m\s*{DIVERGED}!", ansi), "diverged cell not red"
    assert re.search(rf"\x1b\[33m\s*{v.cells[STALE].soc_pct:.2f}", ansi), "stale SOC not yellow"
    assert not re.search(r"\x1b\[(1;)?3[13]m\s*0~?!?\x1b", ansi)  # cell 0 is neither


def test_values_rejected_one_by_one_are_shown_beside_rejected_frames() -> None:
    """A voltage range the cells read above rejects every voltage value, never a frame: the counters
    line said "rejected 0" while the decoder counted each value out of range."""
    cfg = build_config({"pack": {"n_cells": 12}, "mapping": {"voltage_range_v": [1.5, 3.0]}})
    decoder, builder = FrameDecoder(cfg), FrameBuilder(cfg)
    for k in range(5):
        for frame in builder.frames_for_sample(0.1 * k, 1.0, np.full(12, 3.6), np.full(3, 25.0)):
            decoder.feed(frame)
    assert decoder.rejected == 0 and decoder.counters["out_of_range"] == 60
    v = _view()
    v.health = HealthMonitor(pack="p").payload(1.0, decoder.counters)
    assert v.health.counters["values_rejected"] == 60
    assert "rejected 0 frames, 60 values" in _render(v, "cell", 120)


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_once_against_a_real_publisher(tmp_path) -> None:
    """``socd watch --once`` joins late through the snapshot queryable on loopback (no multicast)."""
    port = _port()
    section = argparse.Namespace(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], connect=[], scouting_multicast=False,
                                 key_prefix="bms", pack_id="w", config_file=None)
    health = HealthMonitor(pack="w")
    pub = ZenohPublisher(section, 8, health)
    n = 12
    soc = np.linspace(0.5, 0.61, n)[::-1].copy()
    r = PublishRound(t_s=5.0, soc=soc, soc_std=np.full(n, 0.01), voltage_v=np.full(n, 3.7),
                     stale=np.zeros(n, bool), params={}, health=health.payload(5.0), status_flags={},
                     current_a=1.0, pack=pack_view(soc, 2.5, OcvEnergy(OcvTable.from_points(
                         np.array([0.0, 1.0]), np.array([3.0, 4.2])))))
    pub.start()
    try:
        pub.submit(r)
        plot = tmp_path / "soc.png"
        args = argparse.Namespace(connect=f"tcp/127.0.0.1:{port}", prefix="bms", pack="w", plot=plot, once=True,
                                  timeout=10.0, sort="soc")
        out = io.StringIO()
        assert asyncio.run(watch(args, out)) == 0
    finally:
        pub.stop()
    text = out.getvalue()
    assert "socd watch bms/w" in text and f"{n} cells" in text
    assert _cells_in_order(text) == list(range(n))[::-1]  # lowest SOC first: the last cell
    # the pack line: equal capacities, so the weakest cell is the lowest SOC, the last one
    assert f"weakest {n - 1}" in text and f"imbalance {0.11 * 2.5:.3f} Ah" in text
    assert plot.stat().st_size > 1000


class _Terminal(io.StringIO):
    """A stream that says it is a terminal, so watch takes its live (rich.live) path."""

    def isatty(self) -> bool:
        return True


def test_live_view_redraws_from_subscriptions() -> None:
    port = _port()
    section = argparse.Namespace(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], connect=[], scouting_multicast=False,
                                 key_prefix="bms", pack_id="live", config_file=None)
    health = HealthMonitor(pack="live")
    pub = ZenohPublisher(section, 8, health)
    n = 96

    def round_(t: float) -> PublishRound:
        return PublishRound(t_s=t, soc=np.full(n, 0.7), soc_std=np.full(n, 0.01), voltage_v=np.full(n, 3.7),
                            stale=np.arange(n) == STALE, params={}, health=health.payload(t), status_flags={},
                            current_a=2.0)

    out = _Terminal()
    args = argparse.Namespace(connect=f"tcp/127.0.0.1:{port}", prefix="bms", pack="live", plot=None, once=False,
                              timeout=5.0, sort="cell")

    async def scenario() -> None:
        task = asyncio.create_task(watch(args, out))
        for k in range(30):  # keep publishing while the view subscribes and redraws
            pub.submit(round_(float(k)))
            await asyncio.sleep(0.1)
            if "t 2" in out.getvalue():
                break
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    pub.start()
    try:
        pub.submit(round_(0.0))
        asyncio.run(scenario())
    finally:
        pub.stop()
    text = out.getvalue()
    assert "\x1b[?1049h" in text  # the alternate screen: the header never scrolls away
    assert f"{n} cells" in text and f"{STALE}~" in text
    assert re.search(r"t [2-9]\.0 s", text), "no redraw with a later round"
