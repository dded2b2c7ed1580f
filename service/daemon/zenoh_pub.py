"""Zenoh publication that can never block estimation (DESIGN §5, §6).

The event loop hands a :class:`PublishRound` (plain arrays, copied) to
:meth:`ZenohPublisher.submit`, which appends it to a bounded deque
(``output.queue_size`` rounds) and returns at once; when the deque is full the oldest
round is dropped and counted (``zenoh_dropped_rounds``, and ``zenoh_dropped`` messages),
because a newer round supersedes it anyway.  One publisher thread owns the Zenoh session:
it opens it (retrying with exponential backoff while it fails, flag ``zenoh_down``),
turns rounds into JSON payloads (:mod:`service.daemon.payloads`) and ``put``s them with
``CongestionControl.DROP`` so a slow subscriber cannot back up into us.

Counting (health): ``zenoh_messages`` = every ``put`` made; ``zenoh_unmatched`` = the
puts among them that no subscriber matched at the time (Zenoh's publisher matching status):
with the router down or nobody subscribed they reach no one, so they are counted as
undelivered rather than as sent.  ``zenoh_dropped`` = messages never put (queue overflow,
a failing session).

The ``<prefix>/<pack>/snapshot`` queryable answers from Zenoh's own thread out of the
latest round (guarded by a lock), so a late joiner is served even while the loop is busy.
Zenoh's Python API has no asyncio interface; nothing here touches the event loop.

Session config: ``mode``, ``listen`` (always set explicitly: Zenoh's unset default
listens on every interface), ``connect``, and multicast scouting as configured (off by
default and in every test).  ``[zenoh] config_file`` names a Zenoh JSON5 config (TLS,
access control, routers, ...) read with ``zenoh.Config.from_file``; those four settings of
the section are then applied only where the file leaves them at Zenoh's default, so a key
the file sets always wins (see :func:`config_from_section`).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.cell.parameters import PARAMETER_NAMES
from service.daemon.health import HealthMonitor
from service.daemon.payloads import CellParams, CellSoc, Health, Keys, Snapshot, Summary, keys

log = logging.getLogger(__name__)

#: how often the publisher checks that a configured ``connect`` peer is actually connected
PEER_CHECK_S = 1.0


def zenoh_config(mode: str, listen: Sequence[str], connect: Sequence[str], scouting_multicast: bool):
    """A ``zenoh.Config`` with every network-facing knob set explicitly."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(scouting_multicast)))
    return cfg


class ZenohConfigError(ValueError):
    """``zenoh.config_file`` cannot be read or parsed; the message names the file."""


#: the section's network keys, as Zenoh config paths
SECTION_KEYS = ("mode", "listen/endpoints", "connect/endpoints", "scouting/multicast/enabled")


def config_from_section(z: Any):
    """A ``zenoh.Config`` from the ``[zenoh]`` section of :class:`service.config.SocdConfig`.

    With ``config_file``: the user's file, then each of :data:`SECTION_KEYS` from the section
    only where the file leaves it at Zenoh's default value (the file wins where it sets one).
    Raises :class:`ZenohConfigError` for a missing or malformed file.
    """
    path = getattr(z, "config_file", None)
    if path is None:
        return zenoh_config(z.mode, z.listen, z.connect, z.scouting_multicast)
    import zenoh

    try:
        cfg = zenoh.Config.from_file(str(path))
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError for a missing or malformed file
        detail = str(exc).split(" at /")[0].strip().replace("\n", " ")
        raise ZenohConfigError(f"zenoh.config_file: {path}: {' '.join(detail.split())}") from None
    default = zenoh.Config()
    ours = dict(zip(SECTION_KEYS, (z.mode, list(z.listen), list(z.connect), bool(z.scouting_multicast))))
    for key, value in ours.items():
        if cfg.get_json(key) == default.get_json(key):
            cfg.insert_json5(key, json.dumps(value))
    return cfg


@dataclass
class PublishRound:
    """One publication's worth of estimator output (arrays are the publisher's to keep)."""

    t_s: float
    soc: np.ndarray
    soc_std: np.ndarray
    voltage_v: np.ndarray
    stale: np.ndarray
    params: dict[str, np.ndarray]
    health: Health
    status_flags: dict[str, bool]
    current_a: float | None = None
    v_pred: np.ndarray | None = None
    resets: np.ndarray | None = None
    #: wall time of the newest frame in this round, for the frame→publication latency
    frame_wall_s: float | None = None
    initialised: bool = True
    #: :meth:`PackEstimator.health` arrays (capacity_ah, capacity_std_ah, capacity_rel, resistance_rel)
    health_cells: dict[str, np.ndarray] | None = None

    @property
    def n_cells(self) -> int:
        return int(np.size(self.soc))


def _num(x: float, scale: float = 1.0, nd: int = 6) -> float | None:
    x = float(x)
    return round(x * scale, nd) if np.isfinite(x) else None


@dataclass
class RoundPayloads:
    cells: list[CellSoc]
    params: list[CellParams]
    summary: Summary
    health: Health


def build_payloads(pack: str, r: PublishRound) -> RoundPayloads:
    """The pydantic payloads of one round (runs on the publisher thread)."""
    n = r.n_cells
    resets = r.resets if r.resets is not None else np.zeros(n, dtype=int)
    soh = r.health_cells or {}

    def soh_value(key: str, i: int, scale: float = 1.0, nd: int = 6) -> float | None:
        return _num(soh[key][i], scale, nd) if key in soh and r.initialised else None
    cells, params = [], []
    for i in range(n):
        ok = r.initialised
        cells.append(CellSoc(
            pack=pack, t_s=r.t_s, cell=i,
            soc_pct=_num(r.soc[i], 100.0, 4) if ok else None,
            soc_std_pct=_num(r.soc_std[i], 100.0, 4) if ok else None,
            voltage_v=_num(r.voltage_v[i], 1.0, 4),
            v_pred_v=_num(r.v_pred[i], 1.0, 4) if (ok and r.v_pred is not None) else None,
            stale=bool(r.stale[i]),
            resets=int(resets[i]),
        ))
        params.append(CellParams(
            pack=pack, t_s=r.t_s, cell=i,
            **{k: (_num(r.params[k][i], 1.0, 9) if k in r.params else None) for k in PARAMETER_NAMES},
            capacity_ah=soh_value("capacity_ah", i, 1.0, 5), capacity_std_ah=soh_value("capacity_std_ah", i, 1.0, 5),
            capacity_pct=soh_value("capacity_rel", i, 100.0, 3), resistance_pct=soh_value("resistance_rel", i, 100.0, 3),
        ))
    soc = np.asarray(r.soc, float)
    good = np.isfinite(soc) & r.initialised
    if good.any():
        idx = np.flatnonzero(good)
        lo, hi = idx[np.argmin(soc[idx])], idx[np.argmax(soc[idx])]
        summary = Summary(
            pack=pack, t_s=r.t_s, n_cells=n,
            soc_mean_pct=_num(soc[idx].mean(), 100.0, 4),
            soc_min_pct=_num(soc[lo], 100.0, 4), soc_max_pct=_num(soc[hi], 100.0, 4),
            cell_min=int(lo), cell_max=int(hi),
            soc_std_max_pct=_num(np.nanmax(r.soc_std[idx]), 100.0, 4),
            current_a=None if r.current_a is None else _num(r.current_a, 1.0, 4),
            n_stale=int(np.count_nonzero(r.stale)), status_flags=r.status_flags,
        )
    else:
        summary = Summary(
            pack=pack, t_s=r.t_s, n_cells=n, soc_mean_pct=None, soc_min_pct=None, soc_max_pct=None,
            cell_min=None, cell_max=None, soc_std_max_pct=None,
            current_a=None if r.current_a is None else _num(r.current_a, 1.0, 4),
            n_stale=int(np.count_nonzero(r.stale)), status_flags=r.status_flags,
        )
    return RoundPayloads(cells, params, summary, r.health)


@dataclass
class _SessionState:
    session: Any = None
    publishers: dict[str, Any] = field(default_factory=dict)
    queryable: Any = None


class ZenohPublisher:
    """Bounded, drop-oldest queue in front of a Zenoh session owned by one thread.

    ``session_factory`` (default: ``zenoh.open(config)``) is injectable so tests can make
    opening fail.  ``expect_peers``: treat "no peer or router connected" as down (set when
    the config has ``connect`` endpoints: then somebody is supposed to be there).
    """

    def __init__(
        self,
        zenoh_section: Any,
        queue_size: int,
        health: HealthMonitor,
        *,
        session_factory: Callable[[], Any] | None = None,
        backoff_initial_s: float = 0.2,
        backoff_max_s: float = 5.0,
    ) -> None:
        self.keys: Keys = keys(zenoh_section.key_prefix, zenoh_section.pack_id)
        self.pack = zenoh_section.pack_id
        self.health = health
        self._factory = session_factory or self._default_factory(zenoh_section)
        self._expect_peers = bool(list(getattr(zenoh_section, "connect", []) or []))
        self._queue: deque[PublishRound] = deque()
        self._maxlen = max(1, int(queue_size))
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._latest: RoundPayloads | None = None
        self._latest_lock = threading.Lock()
        self._backoff_initial = backoff_initial_s
        self._backoff_max = backoff_max_s
        self._state = _SessionState()
        self.rounds_published = 0
        self.messages_published = 0
        self.down = True
        self.health.set_flag("zenoh_down", True)

    @staticmethod
    def _default_factory(z: Any) -> Callable[[], Any]:
        def open_session():
            import zenoh

            return zenoh.open(config_from_section(z))

        return open_session

    # -- loop side ---------------------------------------------------------------------
    def submit(self, r: PublishRound) -> None:
        """Queue a round; never blocks beyond a short lock.  Drops (and counts) the oldest when full."""
        with self._cond:
            if len(self._queue) >= self._maxlen:
                old = self._queue.popleft()
                self.health.count("zenoh_dropped_rounds", flag="publish_drops")
                self.health.count("zenoh_dropped", 2 * old.n_cells + 2)
            self._queue.append(r)
            self._cond.notify()

    def queue_len(self) -> int:
        return len(self._queue)

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="socd-zenoh-publisher", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    # -- publisher thread ----------------------------------------------------------------
    def _set_down(self, down: bool) -> None:
        if down != self.down:
            (log.warning if down else log.info)("zenoh session %s", "down" if down else "up")
        self.down = down
        self.health.set_flag("zenoh_down", down)

    def _open(self) -> bool:
        try:
            session = self._factory()
        except Exception as exc:  # noqa: BLE001 - zenoh raises ZError and friends
            self.health.count("zenoh_open_failures", flag="zenoh_down")
            log.warning("zenoh session failed to open: %s", exc)
            return False
        st = _SessionState(session=session)
        try:
            st.queryable = session.declare_queryable(self.keys.snapshot, self._on_query)
        except Exception as exc:  # noqa: BLE001
            self.health.count("zenoh_open_failures")
            log.warning("zenoh queryable failed: %s", exc)
            self._close_session(st)
            return False
        self._state = st
        self.health.count("zenoh_sessions_opened")
        return True

    def _close_session(self, st: _SessionState | None = None) -> None:
        st = st or self._state
        if st.session is not None:
            try:
                st.session.close()
            except Exception as exc:  # noqa: BLE001
                log.debug("zenoh close: %r", exc)
        if st is self._state:
            self._state = _SessionState()

    def _peers_connected(self) -> bool:
        info = self._state.session.info
        return bool(list(info.peers_zid())) or bool(list(info.routers_zid()))

    def _run(self) -> None:
        delay = self._backoff_initial
        last_peer_check = 0.0
        while not self._stop.is_set():
            if self._state.session is None:
                if not self._open():
                    self._set_down(True)
                    self._stop.wait(delay)
                    delay = min(self._backoff_max, delay * 2)
                    continue
                delay = self._backoff_initial
                self._set_down(False)
            with self._cond:
                if not self._queue and not self._stop.is_set():
                    self._cond.wait(PEER_CHECK_S)
                r = self._queue.popleft() if self._queue else None
            now = time.monotonic()
            if self._expect_peers and now - last_peer_check >= PEER_CHECK_S:
                last_peer_check = now
                try:
                    self._set_down(not self._peers_connected())
                except Exception:  # noqa: BLE001 - a broken session
                    self._fail("session info failed")
                    continue
            if r is None:
                continue
            try:
                self._publish(r)
            except Exception as exc:  # noqa: BLE001
                self.health.count("zenoh_dropped", 2 * r.n_cells + 2, flag="publish_drops")
                self._fail(f"put failed: {exc}")
        self._close_session()

    def _fail(self, why: str) -> None:
        self.health.count("zenoh_session_failures", flag="zenoh_down")
        log.warning("zenoh session failing (%s); reopening", why)
        self._close_session()
        self._set_down(True)

    def _publisher(self, key: str):
        pub = self._state.publishers.get(key)
        if pub is None:
            import zenoh

            pub = self._state.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.DROP, encoding=zenoh.Encoding.APPLICATION_JSON
            )
            self._state.publishers[key] = pub
        return pub

    def _publish(self, r: PublishRound) -> None:
        p = build_payloads(self.pack, r)
        with self._latest_lock:
            self._latest = p
        k = self.keys
        puts = [(k.cell_soc(c.cell), c) for c in p.cells] + [(k.cell_params(c.cell), c) for c in p.params]
        puts += [(k.summary, p.summary), (k.health, p.health)]
        sent = unmatched = 0
        for key, payload in puts:
            pub = self._publisher(key)
            if not pub.matching_status.matching:
                unmatched += 1  # put anyway: a subscriber may be declaring right now
            pub.put(payload.model_dump_json())
            sent += 1
        if r.frame_wall_s is not None:
            self.health.record_latency("publish", time.time() - r.frame_wall_s)
        self.rounds_published += 1
        self.messages_published += sent
        self.health.count("zenoh_messages", sent)
        self.health.count("zenoh_unmatched", unmatched)

    # -- queryable (Zenoh thread) --------------------------------------------------------
    def snapshot_json(self) -> str | None:
        with self._latest_lock:
            p = self._latest
        if p is None:
            return None
        snap = Snapshot(pack=self.pack, t_s=p.summary.t_s, cells=p.cells, params=p.params,
                        summary=p.summary, health=p.health)
        return snap.model_dump_json()

    def _on_query(self, query: Any) -> None:
        try:
            body = self.snapshot_json()
            if body is None:
                query.reply_err(json.dumps({"error": "no estimate yet"}))
            else:
                query.reply(self.keys.snapshot, body)
            self.health.count("zenoh_snapshot_queries")
        except Exception as exc:  # noqa: BLE001 - never let a query kill Zenoh's thread
            self.health.count("zenoh_query_errors")
            log.warning("snapshot query failed: %r", exc)
