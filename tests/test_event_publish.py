"""SOC published when estimated, each key rate-limited, over real Zenoh sessions on loopback
(tcp/127.0.0.1, multicast scouting off); the summary carries the pack view.

- :class:`KeyRateLimit` with explicit clocks: a key goes at most once per interval, the
  newest held-back value goes when the interval has passed, keys do not share a budget;
- an estimate round puts the SOC keys of the cells it names and the summary (with the pack
  view's fields), nothing else, without a full round;
- the daemon, its full-round period an hour: every fed sample's estimate reaches a
  subscriber (no period to wait for); with a 0.25 s interval, a 100 Hz feed is thinned to at
  most one summary per interval and the last estimate still arrives.

No assertion here is on latency; counts and values only.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from zenoh_support import free_port as _port
from zenoh_support import loopback_session as _session

from service.config import DEFAULT_CELL_PROFILE, DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC, build_config
from service.daemon.health import HealthMonitor
from service.daemon.payloads import SUMMARY_SCHEMA_VERSION, CellSoc, Summary
from service.daemon.zenoh_pub import KeyRateLimit, PublishRound, ZenohPublisher
from service.estimators.pack_view import OcvEnergy, pack_view


class _Collector:
    """Subscriber callback (a Zenoh thread): payloads by key, thread-safe."""

    def __init__(self) -> None:
        self.by_key: dict[str, list[str]] = {}
        self.lock = threading.Lock()

    def __call__(self, sample) -> None:
        with self.lock:
            self.by_key.setdefault(str(sample.key_expr), []).append(sample.payload.to_string())

    def get(self, key: str) -> list[str]:
        with self.lock:
            return list(self.by_key.get(key, []))


def _wait(pred, timeout: float = 20.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            raise TimeoutError(f"{what} not met within {timeout} s")
        time.sleep(0.02)


# -- the rate limit on its own ------------------------------------------------------------------
def test_key_rate_limit_holds_per_key_and_keeps_the_newest() -> None:
    lim = KeyRateLimit(0.1)
    assert lim.offer("a", 1, now=0.0)
    lim.sent("a", 0.0)
    assert lim.offer("b", 1, now=0.01)  # another key has its own budget
    lim.sent("b", 0.01)
    assert not lim.offer("a", 2, now=0.03) and not lim.offer("a", 3, now=0.05)
    assert lim.superseded == 1 and lim.next_due() == pytest.approx(0.1)
    assert lim.due(0.09) == []
    assert lim.due(0.1) == [("a", 3)]  # the newest held-back value, once
    lim.sent("a", 0.1)
    assert lim.due(0.5) == [] and lim.next_due() is None
    assert lim.offer("a", 4, now=0.2)  # a full interval later: goes at once
    lim.sent("a", 0.2)
    assert not lim.offer("a", 5, now=0.21, hold=False) and "a" not in lim.pending  # a repeat is skipped
    free = KeyRateLimit(0.0)
    assert all(free.offer("k", i, now=0.0) for i in range(5))


# -- the publisher: estimate rounds --------------------------------------------------------------
def _round(n: int, t: float, health: HealthMonitor, *, full: bool, cells: np.ndarray | None = None) -> PublishRound:
    from service.cell.profile import load_profile

    profile = load_profile(DEFAULT_CELL_PROFILE)
    soc = np.linspace(0.3, 0.7, n) + 0.001 * t
    view = pack_view(soc, profile.effective_capacity_ah, OcvEnergy(profile.ocv_table()), 25.0)
    flags = health.flags()
    return PublishRound(
        t_s=t, soc=soc, soc_std=np.full(n, 0.01), voltage_v=np.full(n, 3.7), stale=np.zeros(n, bool),
        params={"r_ohm": np.full(n, 0.02)} if full else {}, health=health.payload(t, {}, flags) if full else None,
        status_flags=flags, current_a=1.0, v_pred=np.full(n, 3.7), resets=np.zeros(n, dtype=int),
        frame_wall_s=time.time(), pack=view, full=full, cells=cells,
    )


@contextlib.contextmanager
def _connected(pack: str, n: int) -> Iterator[tuple[ZenohPublisher, HealthMonitor, _Collector]]:
    """A publisher (no rate limit) on a loopback port and a subscriber to every key under
    ``bms/<pack>/``, connected: full rounds of ``n`` cells at t = 0 are submitted until one arrives."""
    port = _port()
    health = HealthMonitor(pack=pack)
    section = type("S", (), {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"], "connect": [],
                                 "scouting_multicast": False, "key_prefix": "bms", "pack_id": pack})()
    pub = ZenohPublisher(section, 16, health, min_interval_s=0.0)
    pub.start()
    sub_session = _session(connect=[f"tcp/127.0.0.1:{port}"])
    got = _Collector()
    sub = sub_session.declare_subscriber(f"bms/{pack}/**", got)
    try:
        k = 0
        while not got.get(f"bms/{pack}/summary"):
            assert k < 400, "the subscriber never connected"
            pub.submit(_round(n, 0.0, health, full=True))
            k += 1
            time.sleep(0.05)
        yield pub, health, got
    finally:
        sub.undeclare()
        sub_session.close()
        pub.stop()


def test_estimate_round_puts_only_its_cells_and_the_summary_with_the_pack_view() -> None:
    n = 6
    with _connected("packE", n) as (pub, health, got):
        before = {key: len(v) for key, v in got.by_key.items()}
        cells = np.zeros(n, bool)
        cells[[1, 4]] = True
        pub.submit(_round(n, 7.0, health, full=False, cells=cells))
        _wait(lambda: any(Summary.model_validate_json(p).t_s == 7.0 for p in got.get("bms/packE/summary")),
              what="the estimate's summary")
        new_t = {key: [CellSoc.model_validate_json(p).t_s for p in got.get(key)[before.get(key, 0):]]
                 for key in (f"bms/packE/cell/{i}/soc" for i in range(n))}
        assert 7.0 in new_t["bms/packE/cell/1/soc"] and 7.0 in new_t["bms/packE/cell/4/soc"]
        assert all(7.0 not in new_t[f"bms/packE/cell/{i}/soc"] for i in (0, 2, 3, 5))
        assert all(len(got.get(f"bms/packE/cell/{i}/params")) == before.get(f"bms/packE/cell/{i}/params", 0)
                   for i in range(n))  # no parameters, no health in an estimate round
        s = [Summary.model_validate_json(p) for p in got.get("bms/packE/summary") if '"t_s":7.0' in p][-1]
        assert s.schema_version == SUMMARY_SCHEMA_VERSION
        # the pack view of the round, in the summary: 6 equal cells, the emptiest at 30.7 %
        assert s.weakest_cell == 0 and s.fullest_cell == n - 1
        assert s.usable_soc_pct is not None and s.soc_min_pct < s.usable_soc_pct < s.soc_max_pct
        assert s.imbalance_ah == pytest.approx(0.4 * 2.9, rel=0.05)  # (70.7 − 30.7) % of ~2.9 Ah
        assert s.usable_energy_wh < s.remaining_energy_wh and s.usable_discharge_ah > 0
        assert health.latency_ms()["publish_p50"] is not None  # estimate rounds are the ones timed


# -- the daemon: estimates published as they happen ---------------------------------------------
def _daemon_config(tmp_path: Path, port: int, min_interval_s: float):
    n = 4
    return build_config({
        "cell_profile": str(DEFAULT_CELL_PROFILE),
        "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": n},
        "bus": {"interface": "virtual", "channel": f"ev-{port}"},
        # the full round would come only after an hour: whatever arrives here is event-driven
        "output": {"zenoh_period_s": 3600.0, "min_publish_interval_s": min_interval_s, "can_enabled": False},
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"], "connect": [],
                  "scouting_multicast": False, "key_prefix": "bms", "pack_id": "packD"},
        "checkpoint": {"path": str(tmp_path / "state.ckpt"), "interval_s": 3600},
    })


def _run_daemon(config, scenario) -> None:
    from service.daemon.daemon import Daemon

    bus = can.Bus(interface="virtual", channel=config.bus.channel)

    async def main() -> None:
        d = Daemon(config, bus, install_signal_handlers=False)
        stop = asyncio.Event()
        run = asyncio.create_task(d.run(stop))
        await d.wait_started()
        try:
            await scenario(d)
        finally:
            stop.set()
            await asyncio.wait_for(run, 15)

    try:
        asyncio.run(main())
    finally:
        bus.shutdown()


def _sample(n: int, t: float, current: float = 1.0):
    from service.bus.types import PackSample

    return PackSample(t_s=t, current_a=current, voltage_v=np.linspace(3.55, 3.65, n),
                      temperature_c=np.full(n, 25.0), fresh=np.ones(n, dtype=bool))


def test_daemon_publishes_each_estimate_without_waiting_for_a_period(tmp_path: Path) -> None:
    port = _port()
    config = _daemon_config(tmp_path, port, min_interval_s=0.0)
    n = config.pack.n_cells
    got = _Collector()
    sub_session = _session(connect=[f"tcp/127.0.0.1:{port}"])
    sub = sub_session.declare_subscriber("bms/packD/**", got)

    async def scenario(d) -> None:
        t = 100.0
        end = time.monotonic() + 20
        while not got.get("bms/packD/summary"):  # until the subscriber's session is connected
            assert time.monotonic() < end, "nothing arrived"
            d.on_sample(_sample(n, t), time.time())
            t += 0.1
            await asyncio.sleep(0.05)
        for _ in range(5):  # each of these estimates must arrive on its own
            t += 0.1
            d.on_sample(_sample(n, t), time.time())
            want = t
            await asyncio.to_thread(_wait, lambda want=want: any(
                Summary.model_validate_json(p).t_s == want for p in got.get("bms/packD/summary")),
                10.0, f"summary at t={want}")
            cell = CellSoc.model_validate_json(got.get(f"bms/packD/cell/{n - 1}/soc")[-1])
            assert cell.t_s == want and cell.soc_pct == pytest.approx(100 * d.estimator.soc[n - 1], abs=1e-3)
        s = Summary.model_validate_json(got.get("bms/packD/summary")[-1])
        view = d.pack_view()
        assert s.usable_soc_pct == pytest.approx(100 * view.usable_soc, abs=1e-3)
        assert s.weakest_cell == view.weakest_cell and s.remaining_energy_wh == pytest.approx(
            view.remaining_energy_wh, abs=1e-3)
        assert not got.get("bms/packD/health") and not got.get("bms/packD/cell/0/params")  # no full round yet

    try:
        _run_daemon(config, scenario)
    finally:
        sub.undeclare()
        sub_session.close()


def test_daemon_rate_limit_holds_per_key_and_the_last_estimate_arrives(tmp_path: Path) -> None:
    port = _port()
    interval = 0.25
    config = _daemon_config(tmp_path, port, min_interval_s=interval)
    n = config.pack.n_cells
    got = _Collector()
    sub_session = _session(connect=[f"tcp/127.0.0.1:{port}"])
    sub = sub_session.declare_subscriber("bms/packD/**", got)
    result: dict[str, float] = {}

    async def scenario(d) -> None:
        t = 100.0
        end = time.monotonic() + 20
        while not got.get("bms/packD/summary"):
            assert time.monotonic() < end, "nothing arrived"
            d.on_sample(_sample(n, t), time.time())
            t += 0.01
            await asyncio.sleep(0.3)
        before = {k: len(got.get(k)) for k in ("bms/packD/summary", "bms/packD/cell/0/soc")}
        w0 = time.monotonic()
        fed = 0
        while time.monotonic() - w0 < 2.0:  # ~100 Hz for 2 s
            t += 0.01
            d.on_sample(_sample(n, t), time.time())
            fed += 1
            await asyncio.sleep(0.01)
        wall = time.monotonic() - w0
        last = t
        await asyncio.to_thread(_wait, lambda: any(
            Summary.model_validate_json(p).t_s == last for p in got.get("bms/packD/summary")),
            10.0, "the last estimate (held back, then due)")
        await asyncio.sleep(2 * interval)  # nothing more is due; anything late would show now
        result.update(fed=fed, wall=wall, last=last,
                      summaries=len(got.get("bms/packD/summary")) - before["bms/packD/summary"],
                      cell0=len(got.get("bms/packD/cell/0/soc")) - before["bms/packD/cell/0/soc"],
                      rate_limited=d.counters().get("zenoh_rate_limited", 0))

    try:
        _run_daemon(config, scenario)
    finally:
        sub.undeclare()
        sub_session.close()
    bound = result["wall"] / interval + 2  # one per interval, plus the edges
    assert result["fed"] > 3 * bound  # the feed really was faster than the limit
    assert 2 <= result["summaries"] <= bound and 2 <= result["cell0"] <= bound
    assert result["rate_limited"] > 0


def test_fast_cell_json_is_the_model_s_json() -> None:
    """The publisher's one-pass JSON for the SOC keys equals the CellSoc model's, field for field
    (NaN and inf as null, stale flags, resets, before and after the first estimate)."""
    import json

    from service.daemon.zenoh_pub import cell_soc_json, cell_soc_payload

    n = 9
    soc = np.linspace(0.1, 0.9, n)
    soc[2], soc[3] = np.nan, np.inf
    volts = np.full(n, 3.712345678)
    volts[5] = np.nan
    for initialised in (True, False):
        for v_pred in (np.full(n, 3.70001), None):
            r = PublishRound(t_s=1732443600.123456, soc=soc, soc_std=np.full(n, 0.0123456), voltage_v=volts,
                             stale=np.arange(n) % 3 == 0, params={}, health=None, status_flags={},
                             v_pred=v_pred, resets=np.arange(n), initialised=initialised, full=False)
            idx = np.array([0, 2, 3, 5, 8])
            fast = cell_soc_json('pack "q"', r, idx)
            for i, body in zip(idx, fast):
                model = cell_soc_payload('pack "q"', r, int(i))
                assert json.loads(body) == json.loads(model.model_dump_json())
                assert CellSoc.model_validate_json(body) == model


def test_fast_params_json_is_the_model_s_json() -> None:
    """The one-pass JSON for the parameter keys equals the CellParams model's, field for field:
    a parameter missing from the round, NaN and inf as null, the health fields present or not,
    before and after the first estimate."""
    import json

    from service.cell.parameters import PARAMETER_NAMES
    from service.daemon.payloads import CellParams
    from service.daemon.zenoh_pub import cell_params_json, cell_params_payload
    from service.estimators.state_of_health import CellHealth

    n = 7
    params = {name: np.linspace(0.001, 2.0, n) * (k + 1) for k, name in enumerate(PARAMETER_NAMES[1:])}
    params["r_ct"][1], params["m"][4] = np.nan, np.inf
    health = CellHealth(capacity_ah=np.linspace(2.7, 2.9, n), capacity_std_ah=np.full(n, 0.0123456),
                        capacity_rel=np.linspace(0.95, 1.02, n), resistance_rel=np.full(n, 1.0512345))
    health.capacity_ah[3] = np.nan
    idx = np.array([0, 1, 3, 4, 6])
    for initialised in (True, False):
        for health_cells in (health, None):
            r = PublishRound(t_s=1732443600.123456, soc=np.full(n, 0.5), soc_std=np.full(n, 0.01),
                             voltage_v=np.full(n, 3.7), stale=np.zeros(n, bool), params=params, health=None,
                             status_flags={}, initialised=initialised, health_cells=health_cells)
            for i, body in zip(idx, cell_params_json('pack "q"', r, idx)):
                model = cell_params_payload('pack "q"', r, int(i))
                assert json.loads(body) == json.loads(model.model_dump_json())
                assert CellParams.model_validate_json(body) == model


def test_a_full_round_repeats_only_what_no_estimate_round_refreshed() -> None:
    """While estimate rounds flow, a full round puts parameters and health but not the SOC keys
    they just refreshed (a repeat would take the next estimate's rate-limit slot); a cell whose
    stale flag changed goes out with it, and once estimates stop every SOC key goes out again."""
    n = 5

    def soc_times(i: int) -> list[float]:
        return [CellSoc.model_validate_json(p).t_s for p in got.get(f"bms/packR/cell/{i}/soc")]

    def full_round_done(t: float) -> bool:  # every parameter key of the round has arrived
        return all(f'"t_s":{t}' in "".join(got.get(f"bms/packR/cell/{i}/params")) for i in range(n))

    with _connected("packR", n) as (pub, health, got):
        pub.submit(_round(n, 1.0, health, full=False, cells=np.ones(n, bool)))
        _wait(lambda: all(1.0 in soc_times(i) for i in range(n)), what="the estimate round")
        full = _round(n, 2.0, health, full=True)
        full.stale[3] = True
        pub.submit(full)
        _wait(lambda: full_round_done(2.0), what="the full round's parameters")
        assert 2.0 in soc_times(3)  # its stale flag changed
        assert all(2.0 not in soc_times(i) for i in (0, 1, 2, 4))
        assert any('"t_s":2.0' in p for p in got.get("bms/packR/summary"))  # with the changed cell
        assert any('"t_s":2.0' in p for p in got.get("bms/packR/health"))
        pub.submit(_round(n, 3.0, health, full=True))  # no estimate round since the last full one
        _wait(lambda: full_round_done(3.0), what="the second full round's parameters")
        assert all(3.0 in soc_times(i) for i in range(n))
        assert any('"t_s":3.0' in p for p in got.get("bms/packR/summary"))
