"""Zenoh publication that can never block estimation (DESIGN §5, §6).

The event loop hands a :class:`PublishRound` (plain arrays, copied) to
:meth:`ZenohPublisher.submit`, which appends it to a bounded deque
(``output.queue_size`` rounds) and returns at once; when the deque is full the oldest
round is dropped and counted (``zenoh_dropped_rounds``, and ``zenoh_dropped`` messages),
because a newer round supersedes it anyway.  One publisher thread owns the Zenoh session:
it opens it (retrying with exponential backoff while it fails, flag ``zenoh_down``),
turns rounds into JSON payloads (:mod:`service.daemon.payloads`) and ``put``s them with
``CongestionControl.DROP`` so a slow subscriber cannot back up into us.

Two kinds of round: a *full* round (each cell's parameters, health, and the SOC keys and
summary no estimate round refreshed since the last full round or whose cell's stale flag
changed; the daemon sends one every ``output.zenoh_period_s``) and an *estimate* round
(``full=False``: the SOC keys of the cells in ``r.cells`` and the summary; the daemon sends
one after every estimator step, so a dashboard sees a change within milliseconds).  Every
key is rate-limited on its own: a key put less than ``min_interval_s`` ago is held back,
its newest value put as soon as its interval has passed (counted ``zenoh_rate_limited``
when a newer value replaced a held one); a full round's SOC and summary keys are never
held back, only skipped, and while estimate rounds flow they are not offered at all: a repeat
put would take the next estimate's slot and hold it back by up to ``min_interval_s``.  A full
round's parameter and health keys go out in chunks of :data:`BACKLOG_CHUNK` between estimate rounds, so the hundreds of parameter
payloads never hold an estimate round back (a newer full round replaces what is left of an older
one's, counted ``zenoh_rate_limited``).  The ``publish`` latency is from a frame's wall
time to the ``put`` of the summary of the estimate round that carried it (all its cells
are put before the summary).

Counting (health): ``zenoh_messages`` = every ``put`` made; ``zenoh_unmatched`` = the
puts among them that no subscriber matched at the time (Zenoh's publisher matching status):
with the router down or nobody subscribed they reach no one, so they are counted as
undelivered rather than as sent.  ``zenoh_dropped`` = messages never put (queue overflow,
a failing session).

The ``<prefix>/<pack>/snapshot`` queryable answers from Zenoh's own thread out of the
latest rounds (guarded by a lock), so a late joiner is served even while the loop is busy.
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
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from service.cell.parameters import PARAMETER_NAMES
from service.daemon.health import HealthMonitor
from service.daemon.payloads import CellParams, CellSoc, Health, Keys, Snapshot, Summary, keys
from service.estimators.pack_view import PackView
from service.estimators.state_of_health import CellHealth

log = logging.getLogger(__name__)

#: how often the publisher checks that a configured ``connect`` peer is actually connected
PEER_CHECK_S = 1.0


#: parameter/health keys put between two looks at the queue of estimate rounds
BACKLOG_CHUNK = 16
#: pause between two backlog chunks (cut short by a new round): the estimation loop shares the
#: GIL with this thread, and a thread that never pauses makes it wait for the interpreter's
#: switch interval at every frame it wakes up for
BACKLOG_GAP_S = 0.002


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

    from service.config import special_file_problem

    if (problem := special_file_problem(Path(path))) is not None:  # a pipe would block the read
        raise ZenohConfigError(f"zenoh.config_file: {problem}")

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
    """One publication's worth of estimator output (arrays are the publisher's to keep).

    ``full``: parameters, health and every SOC key offered (the publisher skips those an
    estimate round refreshed since the last full round); otherwise an estimate round: the SOC
    keys of ``cells`` (a bool mask; None = every cell) and the summary, and ``params``/``health``
    may be left empty.
    """

    t_s: float
    soc: np.ndarray
    soc_std: np.ndarray
    voltage_v: np.ndarray
    stale: np.ndarray
    params: dict[str, np.ndarray]
    health: Health | None
    status_flags: dict[str, bool]
    current_a: float | None = None
    v_pred: np.ndarray | None = None
    resets: np.ndarray | None = None
    #: wall time of the newest frame in this round, for the frame→publication latency
    frame_wall_s: float | None = None
    initialised: bool = True
    pack: PackView | None = None
    full: bool = True
    cells: np.ndarray | None = None
    #: :meth:`PackEstimator.health` (None: an estimator without one)
    health_cells: CellHealth | None = None

    @property
    def n_cells(self) -> int:
        return int(np.size(self.soc))

    def cell_indices(self) -> np.ndarray:
        """Cells whose SOC key this round carries."""
        if self.full or self.cells is None:
            return np.arange(self.n_cells)
        return np.flatnonzero(np.asarray(self.cells, dtype=bool))

    @property
    def n_messages(self) -> int:
        """Puts this round makes when nothing is held back."""
        return 2 * self.n_cells + 2 if self.full else int(self.cell_indices().size) + 1


def _num(x: float, scale: float = 1.0, nd: int = 6) -> float | None:
    x = float(x)
    return round(x * scale, nd) if np.isfinite(x) else None


@dataclass
class RoundPayloads:
    cells: list[CellSoc]
    params: list[CellParams]
    summary: Summary
    health: Health | None


def cell_soc_payload(pack: str, r: PublishRound, i: int) -> CellSoc:
    ok = r.initialised
    return CellSoc(
        pack=pack, t_s=r.t_s, cell=i,
        soc_pct=_num(r.soc[i], 100.0, 4) if ok else None,
        soc_std_pct=_num(r.soc_std[i], 100.0, 4) if ok else None,
        voltage_v=_num(r.voltage_v[i], 1.0, 4),
        v_pred_v=_num(r.v_pred[i], 1.0, 4) if (ok and r.v_pred is not None) else None,
        stale=bool(r.stale[i]),
        resets=int(r.resets[i]) if r.resets is not None else 0,
    )


def _rounded(x: np.ndarray | None, idx: np.ndarray, scale: float, nd: int, ok: bool = True) -> list[float | None]:
    """``_num`` over ``x[idx]`` (None where non-finite, or everywhere when not ``ok``)."""
    if x is None or not ok:
        return [None] * int(idx.size)
    vals = (np.asarray(x, dtype=float)[idx] * scale).tolist()
    return [round(v, nd) if math.isfinite(v) else None for v in vals]


def _js(v: float | None) -> str:
    return "null" if v is None else repr(v)


def _cell_json_head(model: type[CellSoc | CellParams], pack: str, r: PublishRound) -> str:
    """The fields every per-cell payload of a round starts with, up to the cell index's value."""
    return (f'{{"schema_version":{model.model_fields["schema_version"].default},"pack":{json.dumps(pack)},'
            f'"t_s":{_js(float(r.t_s))},"cell":')


def cell_soc_json(pack: str, r: PublishRound, idx: np.ndarray) -> list[str]:
    """``cell_soc_payload(pack, r, i).model_dump_json()`` for every ``i`` in ``idx``, built in one
    pass over the arrays (the publisher's hot path: a 200-cell round in a fraction of the
    model's time).  The JSON is the model's, field for field; ``tests/test_event_publish.py``
    holds the two equal."""
    idx = np.asarray(idx, dtype=int)
    ok = bool(r.initialised)
    soc = _rounded(r.soc, idx, 100.0, 4, ok)
    std = _rounded(r.soc_std, idx, 100.0, 4, ok)
    volt = _rounded(r.voltage_v, idx, 1.0, 4)
    vpred = _rounded(r.v_pred, idx, 1.0, 4, ok)
    stale = np.asarray(r.stale, dtype=bool)[idx].tolist()
    resets = (np.asarray(r.resets, dtype=int)[idx] if r.resets is not None else np.zeros(idx.size, int)).tolist()
    head = _cell_json_head(CellSoc, pack, r)
    return [
        f'{head}{i},"soc_pct":{_js(a)},"soc_std_pct":{_js(b)},"voltage_v":{_js(v)},"v_pred_v":{_js(vp)},'
        f'"stale":{"true" if st else "false"},"resets":{rs}}}'
        for i, a, b, v, vp, st, rs in zip(idx.tolist(), soc, std, volt, vpred, stale, resets)
    ]


def cell_params_payload(pack: str, r: PublishRound, i: int) -> CellParams:
    """Cell ``i``'s identified parameters and state of health (capacity, resistance growth)."""
    soh = r.health_cells if r.initialised else None
    return CellParams(
        pack=pack, t_s=r.t_s, cell=i,
        **{k: (_num(r.params[k][i], 1.0, 9) if k in r.params else None) for k in PARAMETER_NAMES},
        **{field: (_num(getattr(soh, key)[i], scale, nd) if soh is not None else None)
           for field, key, scale, nd in _SOH_FIELDS},
    )


#: the state-of-health fields of :class:`CellParams`: (payload field, field of
#: :class:`~service.estimators.state_of_health.CellHealth`, scale, decimals)
_SOH_FIELDS = (("capacity_ah", "capacity_ah", 1.0, 5), ("capacity_std_ah", "capacity_std_ah", 1.0, 5),
               ("capacity_pct", "capacity_rel", 100.0, 3), ("resistance_pct", "resistance_rel", 100.0, 3))


def cell_params_json(pack: str, r: PublishRound, idx: np.ndarray) -> list[str]:
    """``cell_params_payload(pack, r, i).model_dump_json()`` for every ``i`` in ``idx``, in one pass
    over the arrays, as :func:`cell_soc_json` does for the SOC keys: a full round puts every cell's
    parameters, and building them one model at a time kept the publisher's thread (and so the
    GIL) busy for tens of milliseconds.  ``tests/test_event_publish.py`` holds the two equal."""
    idx = np.asarray(idx, dtype=int)
    soh = r.health_cells
    columns = [(name, _rounded(r.params.get(name), idx, 1.0, 9)) for name in PARAMETER_NAMES]
    columns += [(field, _rounded(getattr(soh, key, None), idx, scale, nd, bool(r.initialised)))
                for field, key, scale, nd in _SOH_FIELDS]
    head = _cell_json_head(CellParams, pack, r)
    names = [name for name, _ in columns]
    rows = zip(*(values for _, values in columns))
    return [head + str(i) + "".join(f',"{name}":{_js(v)}' for name, v in zip(names, row)) + "}"
            for i, row in zip(idx.tolist(), rows)]


def _pack_fields(v: PackView | None) -> dict[str, Any]:
    """The summary's pack-view fields (all None without a view)."""
    if v is None or not v.ok:
        return {}
    return {
        "usable_soc_pct": _num(v.usable_soc, 100.0, 4),
        "usable_discharge_ah": _num(v.usable_discharge_ah, 1.0, 6),
        "usable_charge_ah": _num(v.usable_charge_ah, 1.0, 6),
        "remaining_energy_wh": _num(v.remaining_energy_wh, 1.0, 3),
        "usable_energy_wh": _num(v.usable_energy_wh, 1.0, 3),
        "imbalance_ah": _num(v.imbalance_ah, 1.0, 6),
        "weakest_cell": v.weakest_cell,
        "fullest_cell": v.fullest_cell,
    }


def summary_payload(pack: str, r: PublishRound) -> Summary:
    n = r.n_cells
    soc = np.asarray(r.soc, float)
    good = np.isfinite(soc) & r.initialised
    current = None if r.current_a is None else _num(r.current_a, 1.0, 4)
    n_stale = int(np.count_nonzero(r.stale))
    if not good.any():
        return Summary(
            pack=pack, t_s=r.t_s, n_cells=n, soc_mean_pct=None, soc_min_pct=None, soc_max_pct=None,
            cell_min=None, cell_max=None, soc_std_max_pct=None, current_a=current,
            n_stale=n_stale, status_flags=r.status_flags,
        )
    idx = np.flatnonzero(good)
    lo, hi = idx[np.argmin(soc[idx])], idx[np.argmax(soc[idx])]
    return Summary(
        pack=pack, t_s=r.t_s, n_cells=n,
        soc_mean_pct=_num(soc[idx].mean(), 100.0, 4),
        soc_min_pct=_num(soc[lo], 100.0, 4), soc_max_pct=_num(soc[hi], 100.0, 4),
        cell_min=int(lo), cell_max=int(hi),
        soc_std_max_pct=_num(np.nanmax(r.soc_std[idx]), 100.0, 4),
        current_a=current, n_stale=n_stale, status_flags=r.status_flags,
        **_pack_fields(r.pack),
    )


def build_payloads(pack: str, r: PublishRound) -> RoundPayloads:
    """Every payload of one round, for every cell (the snapshot, ``socd schema``)."""
    n = r.n_cells
    cells = [cell_soc_payload(pack, r, i) for i in range(n)]
    params = [cell_params_payload(pack, r, i) for i in range(n)]
    return RoundPayloads(cells, params, summary_payload(pack, r), r.health)


class KeyRateLimit:
    """At most one put per key per ``min_interval_s``; what is held back waits, newest wins.

    :meth:`offer` says whether a key may go now; if not, the value is kept as pending and
    :meth:`due` hands it back once its interval has passed.  Times are ``time.monotonic``.
    """

    def __init__(self, min_interval_s: float) -> None:
        self.min_interval_s = max(0.0, float(min_interval_s))
        self.last_put: dict[str, float] = {}
        self.pending: dict[str, Any] = {}
        self.superseded = 0

    def offer(self, key: str, item: Any, now: float, hold: bool = True) -> bool:
        """True: put ``key`` now (and call :meth:`sent`); False: held as pending (with ``hold``),
        or skipped (without: a repeat of a value already put or pending)."""
        last = self.last_put.get(key)
        if last is None or now - last >= self.min_interval_s:
            self.pending.pop(key, None)
            return True
        if not hold:
            return False
        if key in self.pending:
            self.superseded += 1
        self.pending[key] = item
        return False

    def sent(self, key: str, now: float) -> None:
        self.last_put[key] = now

    def next_due(self) -> float | None:
        """Earliest time a pending key may go (None: nothing pending)."""
        if not self.pending:
            return None
        return min(self.last_put[k] for k in self.pending) + self.min_interval_s

    def due(self, now: float) -> list[tuple[str, Any]]:
        """Pending keys whose interval has passed, removed from pending."""
        ready = [k for k in self.pending if now - self.last_put[k] >= self.min_interval_s]
        return [(k, self.pending.pop(k)) for k in ready]


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
    ``min_interval_s``: the per-key rate limit (:class:`KeyRateLimit`; 0 = none).
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
        min_interval_s: float = 0.0,
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
        #: newest round of any kind (cells, summary) and newest full one (params, health)
        self._latest: PublishRound | None = None
        self._latest_full: PublishRound | None = None
        self._latest_lock = threading.Lock()
        self._limit = KeyRateLimit(min_interval_s)
        #: a full round's parameter and health keys still to put (see the module doc)
        self._backlog: deque[tuple[str, tuple[PublishRound, str, int]]] = deque()
        self._soc_keys: list[str] = []
        self._params_keys: list[str] = []
        #: SOC and summary keys an estimate round put since the last full round, and the stale
        #: flag each cell's SOC key last went out with (see :meth:`_repeats`)
        self._refreshed: set[str] = set()
        self._stale_put: dict[int, bool] = {}
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
                self.health.count("zenoh_dropped", old.n_messages)
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
                    self._cond.wait(self._wait_s())
                r = self._queue.popleft() if self._queue else None
            now = time.monotonic()
            if self._expect_peers and now - last_peer_check >= PEER_CHECK_S:
                last_peer_check = now
                try:
                    self._set_down(not self._peers_connected())
                except Exception:  # noqa: BLE001 - a broken session
                    self._fail("session info failed")
                    continue
            try:
                if r is not None:
                    self._publish(r)
                self._flush_due()
                if not self._queue and self._backlog:
                    chunk = [self._backlog.popleft() for _ in range(min(BACKLOG_CHUNK, len(self._backlog)))]
                    self._put_all(chunk)
            except Exception as exc:  # noqa: BLE001
                lost = (r.n_messages if r is not None else 0) + len(self._limit.pending) + len(self._backlog)
                self._limit.pending.clear()
                self._backlog.clear()
                self.health.count("zenoh_dropped", lost, flag="publish_drops")
                self._fail(f"put failed: {exc}")
        self._close_session()

    def _wait_s(self) -> float:
        """How long the thread may sleep: until the next held-back key is due, at most
        BACKLOG_GAP_S with a backlog to put, else PEER_CHECK_S."""
        cap = BACKLOG_GAP_S if self._backlog else PEER_CHECK_S
        due = self._limit.next_due()
        if due is None:
            return cap
        return min(cap, max(0.0, due - time.monotonic()))

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
        """Put the round's keys that the rate limit lets go now; hold back the rest."""
        with self._latest_lock:
            self._latest = r
            if r.full:
                self._latest_full = r
        k = self.keys
        soc_keys, params_keys = self._cell_keys(r.n_cells)
        items: list[tuple[str, str, int]] = [(soc_keys[i], "soc", i) for i in r.cell_indices().tolist()]
        items.append((k.summary, "summary", -1))
        if r.full:
            items = self._repeats(r, items)
            slow = [(params_keys[i], "params", i) for i in range(r.n_cells)]
            if r.health is not None:
                slow.append((k.health, "health", -1))
            self.health.count("zenoh_rate_limited", len(self._backlog))  # superseded by this round's values
            self._backlog = deque((key, (r, kind, i)) for key, kind, i in slow)
        now = time.monotonic()
        superseded = self._limit.superseded
        # A full round's SOC and summary repeat what the estimate rounds already put (the
        # estimator has not moved since): held back by the limit, they are skipped, not queued.
        repeat = r.full
        self._put_all([(key, (r, kind, i)) for key, kind, i in items
                       if self._limit.offer(key, (r, kind, i), now, hold=not (repeat and kind in ("soc", "summary")))])
        self.health.count("zenoh_rate_limited", self._limit.superseded - superseded)
        self.rounds_published += 1

    def _repeats(self, r: PublishRound, items: list[tuple[str, str, int]]) -> list[tuple[str, str, int]]:
        """A full round's SOC and summary keys worth putting: those no estimate round put since the
        previous full round (samples stopped, or the cell is not measured), and a cell whose stale
        flag differs from the one its key last carried.  The summary goes with any of them.  While
        estimate rounds flow, a full round's repeats would only take their rate-limit slot."""
        stale = np.asarray(r.stale, dtype=bool)
        soc = [(key, kind, i) for key, kind, i in items if kind == "soc"
               and (key not in self._refreshed or self._stale_put.get(i) != bool(stale[i]))]
        summary = [(key, kind, i) for key, kind, i in items if kind == "summary"
                   and (soc or key not in self._refreshed)]
        self._refreshed.clear()
        return soc + summary

    def _cell_keys(self, n: int) -> tuple[list[str], list[str]]:
        """The per-cell key expressions (made once: a round uses hundreds of them)."""
        if len(self._soc_keys) < n:
            self._soc_keys = [self.keys.cell_soc(i) for i in range(n)]
            self._params_keys = [self.keys.cell_params(i) for i in range(n)]
        return self._soc_keys, self._params_keys

    def _flush_due(self) -> None:
        """Put the held-back keys whose interval has passed (their newest values)."""
        if self._limit.pending:
            self._put_all(self._limit.due(time.monotonic()))

    def _put_all(self, items: list[tuple[str, tuple[PublishRound, str, int]]]) -> None:
        bodies = self._bodies(items)
        unmatched = 0
        for (key, (r, kind, _)), body in zip(items, bodies):
            pub = self._publisher(key)
            if not pub.matching_status.matching:
                unmatched += 1  # put anyway: a subscriber may be declaring right now
            pub.put(body)
            if kind == "summary" and not r.full and r.frame_wall_s is not None:
                self.health.record_latency("publish", time.time() - r.frame_wall_s)
        now = time.monotonic()
        for key, (r, kind, i) in items:
            self._limit.sent(key, now)
            if kind == "soc":
                self._stale_put[i] = bool(r.stale[i])
            if not r.full and kind in ("soc", "summary"):
                self._refreshed.add(key)
        self.messages_published += len(items)
        self.health.count("zenoh_messages", len(items))
        self.health.count("zenoh_unmatched", unmatched)

    def _bodies(self, items: list[tuple[str, tuple[PublishRound, str, int]]]) -> list[str]:
        """The JSON of each item; per-cell bodies built per round and kind in one pass."""
        cell_json: dict[tuple[str, int, int], str] = {}  # (kind, round id, cell) -> JSON
        by_round: dict[tuple[str, int], tuple[PublishRound, list[int]]] = {}
        for _, (r, kind, i) in items:
            if kind in ("soc", "params"):
                by_round.setdefault((kind, id(r)), (r, []))[1].append(i)
        for (kind, rid), (r, cells) in by_round.items():
            build = cell_soc_json if kind == "soc" else cell_params_json
            cell_json.update(zip(((kind, rid, c) for c in cells), build(self.pack, r, np.array(cells, dtype=int))))
        bodies = []
        for _, (r, kind, i) in items:
            if kind in ("soc", "params"):
                bodies.append(cell_json[(kind, id(r), i)])
            elif kind == "summary":
                bodies.append(summary_payload(self.pack, r).model_dump_json())
            else:
                bodies.append(r.health.model_dump_json())
        return bodies

    # -- queryable (Zenoh thread) --------------------------------------------------------
    def snapshot_json(self) -> str | None:
        """The latest state: cells and summary from the newest round, parameters and health from
        the newest full round (None before the first full round)."""
        with self._latest_lock:
            r, full = self._latest, self._latest_full
        if r is None or full is None or full.health is None:
            return None
        n = r.n_cells
        cells = [cell_soc_payload(self.pack, r, i) for i in range(n)]
        params = [cell_params_payload(self.pack, full, i) for i in range(min(n, full.n_cells))]
        snap = Snapshot(pack=self.pack, t_s=r.t_s, cells=cells, params=params,
                        summary=summary_payload(self.pack, r), health=full.health)
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
