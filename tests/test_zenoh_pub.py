"""Zenoh publication against real sessions on loopback (tcp/127.0.0.1, multicast scouting off).

- every key carries a payload that validates against its pydantic model and its schema_version;
- a late joiner gets every cell's latest state from the ``snapshot`` queryable;
- the peer absent, then back: estimation never pauses, ``zenoh_down`` is raised then
  cleared, publishing resumes; a session that fails to open is retried with backoff;
- a slow consumer never stalls the producer: the bounded queue drops the oldest rounds
  and counts them.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest
import zenoh
from zenoh_support import free_port as _port
from zenoh_support import loopback_session as _session

from service.config import DEFAULT_CELL_PROFILE, DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC, build_config
from service.daemon.health import HealthMonitor
from service.daemon.payloads import (
    SCHEMA_VERSION,
    SUMMARY_SCHEMA_VERSION,
    CellParams,
    CellSoc,
    Health,
    Snapshot,
    Summary,
)
from service.daemon.zenoh_pub import PublishRound, ZenohPublisher, zenoh_config


class _Section:
    """The ``[zenoh]`` config section, as the publisher reads it."""

    def __init__(self, port: int, connect: list[str] | None = None, mode: str = "peer") -> None:
        self.mode = mode
        self.listen = [f"tcp/127.0.0.1:{port}"]
        self.connect = connect or []
        self.scouting_multicast = False
        self.key_prefix = "bms"
        self.pack_id = "packT"


def _round(n: int, k: int, health: HealthMonitor) -> PublishRound:
    soc = np.linspace(0.2, 0.9, n) - 0.001 * k
    flags = health.flags()
    return PublishRound(
        t_s=float(k), soc=soc, soc_std=np.full(n, 0.01), voltage_v=np.full(n, 3.7),
        stale=np.arange(n) == 1, params={"r_ohm": np.full(n, 0.02), "m": np.full(n, 0.8)},
        health=health.payload(float(k), {}, flags), status_flags=flags, current_a=1.5,
        v_pred=np.full(n, 3.69), resets=np.zeros(n, dtype=int), frame_wall_s=time.time(),
    )


class _Collector:
    """Subscriber callback (runs on a Zenoh thread): keeps payloads by key, thread-safe."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.by_key: dict[str, list[str]] = {}
        self.lock = threading.Lock()
        self.delay_s = delay_s

    def __call__(self, sample) -> None:
        if self.delay_s:
            time.sleep(self.delay_s)
        with self.lock:
            self.by_key.setdefault(str(sample.key_expr), []).append(sample.payload.to_string())

    def count(self) -> int:
        with self.lock:
            return sum(len(v) for v in self.by_key.values())

    def wait(self, pred, timeout: float = 30.0) -> None:
        end = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > end:
                raise TimeoutError(f"condition not met; have {self.count()} messages")
            time.sleep(0.02)


@pytest.fixture
def publisher():
    made: list[ZenohPublisher] = []

    def make(section: _Section, queue_size: int = 16, **kw) -> tuple[ZenohPublisher, HealthMonitor]:
        health = HealthMonitor(pack=section.pack_id)
        pub = ZenohPublisher(section, queue_size, health, **kw)
        pub.start()
        made.append(pub)
        return pub, health

    yield make
    for p in made:
        p.stop()


def test_messages_have_valid_schema(publisher) -> None:
    port = _port()
    pub, health = publisher(_Section(port))
    sub_session = _session(connect=[f"tcp/127.0.0.1:{port}"])
    try:
        got = _Collector()
        sub = sub_session.declare_subscriber("bms/*/cell/*/soc", got)
        sub2 = sub_session.declare_subscriber("bms/packT/**", got)
        n = 6
        deadline = time.monotonic() + 10
        k = 0
        while not all(f"bms/packT/cell/{i}/params" in got.by_key for i in range(n)):
            assert time.monotonic() < deadline, "nothing received"
            pub.submit(_round(n, k, health))
            k += 1
            time.sleep(0.05)
        got.wait(lambda: "bms/packT/health" in got.by_key and "bms/packT/summary" in got.by_key)
        for i in range(n):
            c = CellSoc.model_validate_json(got.by_key[f"bms/packT/cell/{i}/soc"][-1])
            assert c.schema_version == SCHEMA_VERSION and c.cell == i and c.pack == "packT"
            assert 0.0 <= c.soc_pct <= 100.0 and c.soc_std_pct == pytest.approx(1.0)
            assert c.stale is (i == 1)
            p = CellParams.model_validate_json(got.by_key[f"bms/packT/cell/{i}/params"][-1])
            assert p.r_ohm == pytest.approx(0.02) and p.c_df is None
        s = Summary.model_validate_json(got.by_key["bms/packT/summary"][-1])
        assert s.schema_version == SUMMARY_SCHEMA_VERSION and s.n_cells == n and s.n_stale == 1 and s.cell_max == n - 1
        h = Health.model_validate_json(got.by_key["bms/packT/health"][-1])
        assert h.schema_version == SCHEMA_VERSION and "zenoh_down" in h.status_flags
        # the wildcard a dashboard uses sees every cell's SOC too
        assert json.loads(got.by_key["bms/packT/cell/0/soc"][-1])["schema_version"] == SCHEMA_VERSION
        assert not pub.down and health.counters["zenoh_messages"] > 0
        sub.undeclare()
        sub2.undeclare()
    finally:
        sub_session.close()


def test_late_joiner_gets_snapshot(publisher) -> None:
    port = _port()
    pub, health = publisher(_Section(port))
    n = 5
    for k in range(3):
        pub.submit(_round(n, k, health))
    end = time.monotonic() + 10
    while pub.rounds_published < 3:
        assert time.monotonic() < end
        time.sleep(0.02)
    late = _session(connect=[f"tcp/127.0.0.1:{port}"])
    try:
        snap = None
        end = time.monotonic() + 10
        while snap is None and time.monotonic() < end:
            for reply in late.get("bms/packT/snapshot", timeout=2.0):
                if reply.ok is not None:
                    snap = Snapshot.model_validate_json(reply.ok.payload.to_string())
            if snap is None:
                time.sleep(0.1)  # the session may not have finished connecting
        assert snap is not None, "no snapshot reply"
        assert snap.schema_version == SUMMARY_SCHEMA_VERSION and len(snap.cells) == n and len(snap.params) == n
        expected = 100 * (np.linspace(0.2, 0.9, n) - 0.002)  # the last round, k = 2
        np.testing.assert_allclose([c.soc_pct for c in snap.cells], expected, atol=1e-3)
        assert snap.summary.n_cells == n and snap.t_s == 2.0
        assert health.counters["zenoh_snapshot_queries"] >= 1
    finally:
        late.close()


def test_session_that_fails_to_open_is_retried(publisher) -> None:
    port = _port()
    attempts = {"n": 0}

    def flaky():
        attempts["n"] += 1
        if attempts["n"] <= 3:
            # a client with no router refuses to open (a real failure, not a mock)
            return zenoh.open(zenoh_config("client", [], [f"tcp/127.0.0.1:{_port()}"], False))
        return zenoh.open(zenoh_config("peer", [f"tcp/127.0.0.1:{port}"], [], False))

    pub, health = publisher(_Section(port), session_factory=flaky, backoff_initial_s=0.05, backoff_max_s=0.2)
    for k in range(50):  # submitting never blocks while the session is down
        t0 = time.perf_counter()
        pub.submit(_round(4, k, health))
        assert time.perf_counter() - t0 < 0.01
    end = time.monotonic() + 10
    while pub.down:
        assert time.monotonic() < end, "never reopened"
        time.sleep(0.02)
    assert attempts["n"] == 4
    assert health.counters["zenoh_open_failures"] == 3
    assert health.counters["zenoh_dropped_rounds"] > 0  # queue_size 16 < 50 rounds while down


def test_slow_consumer_never_stalls_and_drops_are_counted(publisher) -> None:
    port = _port()
    pub, health = publisher(_Section(port), queue_size=2)
    sub_session = _session(connect=[f"tcp/127.0.0.1:{port}"])
    try:
        slow = _Collector(delay_s=0.002)
        sub = sub_session.declare_subscriber("bms/packT/**", slow)
        # until the subscriber's session has connected a round is lost, so keep publishing one until
        # it arrives (a single round published too early, on a loaded machine, never does)
        end = time.monotonic() + 30.0
        warmup = 0
        while slow.count() == 0:
            assert time.monotonic() < end, "the subscriber never received a round"
            pub.submit(_round(50, 0, health))
            warmup += 1
            time.sleep(0.2)
        dropped_before = health.counters["zenoh_dropped_rounds"]
        worst = total = 0.0
        rounds = 300
        for k in range(rounds):
            r = _round(50, k, health)
            t0 = time.perf_counter()
            pub.submit(r)
            dt = time.perf_counter() - t0
            worst, total = max(worst, dt), total + dt
        # The consumer needs ~0.2 s per round (102 messages x 2 ms): had publishing been
        # synchronous, 300 submits would take a minute.  What is left is GIL scheduling
        # between this thread and the publisher's (switch interval 5 ms).
        assert total < 0.5, f"300 submits took {total:.2f} s"
        assert worst < 0.1, f"submit blocked for {worst * 1e3:.1f} ms"
        assert health.counters["zenoh_dropped_rounds"] > dropped_before
        assert health.counters["zenoh_dropped"] == 102 * health.counters["zenoh_dropped_rounds"]
        assert health.flags()["publish_drops"]
        assert pub.rounds_published + health.counters["zenoh_dropped_rounds"] <= rounds + warmup
        sub.undeclare()
    finally:
        sub_session.close()


# -- the daemon: peer absent, then back ------------------------------------------------------
def _profile_path() -> Path:
    return DEFAULT_CELL_PROFILE  # the bundled Panasonic NCR18650PF profile


def test_peer_absent_then_back_estimation_continues(tmp_path: Path) -> None:
    from service.bus.types import PackSample
    from service.daemon.daemon import Daemon

    n = 4
    own, peer = _port(), _port()
    config = build_config({
        "cell_profile": str(_profile_path()),
        "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": n},
        "bus": {"interface": "virtual", "channel": f"zp-{own}"},
        "output": {"zenoh_period_s": 0.05, "can_enabled": False},
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{own}"], "connect": [f"tcp/127.0.0.1:{peer}"],
                  "scouting_multicast": False, "key_prefix": "bms", "pack_id": "packZ"},
        "checkpoint": {"path": str(tmp_path / "state.ckpt"), "interval_s": 60},
    })
    bus = can.Bus(interface="virtual", channel=config.bus.channel)
    got = _Collector()

    async def scenario() -> None:
        d = Daemon(config, bus, install_signal_handlers=False)
        stop = asyncio.Event()
        run = asyncio.create_task(d.run(stop))
        await d.wait_started()
        t = 0.0

        async def feed(seconds: float) -> None:
            nonlocal t
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                d.on_sample(PackSample(t_s=t, current_a=1.0, voltage_v=np.full(n, 3.6),
                                       temperature_c=np.full(n, 25.0), fresh=np.ones(n, dtype=bool)),
                            time.time())
                t += 0.1
                await asyncio.sleep(0.01)

        await feed(1.5)  # nobody at the connect endpoint
        steps_absent = d.steps
        assert steps_absent > 50
        assert d.status_flags()["zenoh_down"]
        assert d.publish_round().health.status_flags["zenoh_down"]
        c = d.counters()  # nobody subscribed: every put so far reached no one, and says so
        assert c["zenoh_messages"] > 0 and c["zenoh_unmatched"] >= c["zenoh_messages"] - 2 * n - 2

        router = _session("router", listen=[f"tcp/127.0.0.1:{peer}"])
        try:
            router.declare_subscriber("bms/packZ/**", got)
            end = time.monotonic() + 15
            while got.count() < 20 or d.status_flags()["zenoh_down"]:
                assert time.monotonic() < end, "publishing did not resume"
                await feed(0.1)
            assert d.steps > steps_absent
            h = Health.model_validate_json(got.by_key["bms/packZ/health"][-1])
            assert h.counters["zenoh_messages"] > 0
            steps_back = d.steps
            unmatched_back = d.counters()["zenoh_unmatched"]

            router.close()  # the peer goes away again
            await feed(2.5)
            assert d.steps > steps_back + 50 and d.status_flags()["zenoh_down"]
            # puts during the outage are counted as undelivered, not only as sent
            assert d.counters()["zenoh_unmatched"] >= unmatched_back + 10 * (2 * n + 2)
        finally:
            if not router.is_closed():
                router.close()
        stop.set()
        await asyncio.wait_for(run, 15)

    try:
        asyncio.run(scenario())
    finally:
        bus.shutdown()
