"""An optional Prometheus ``/metrics`` endpoint for the daemon (``[metrics]`` in the config).

Off by default; binds ``127.0.0.1`` unless the config says otherwise.  It exports, from a
registry of its own (never the process-global one):

- ``socd_events_total{reason=...}``: every health counter by reason (frames in, rejections
  by reason, bus reconnects, Zenoh drops, filter resets, ...), read at scrape time;
- ``socd_status_flag{flag=...}``: the status word's flags, 0 or 1;
- ``socd_uptime_seconds`` and ``socd_cells``;
- ``socd_latency_seconds{stage="estimate"|"publish"}``: a histogram of the time from a
  frame's timestamp to the end of the estimator step it triggered (``estimate``) and to the
  Zenoh ``put`` of the round that carries it (``publish``).

The HTTP server is prometheus_client's own (a daemon thread); scrapes never touch the event
loop.  Needs ``prometheus-client`` (the ``metrics`` extra).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping
from typing import Any

log = logging.getLogger(__name__)

#: histogram buckets for frame-to-estimate/publication latency, seconds
LATENCY_BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)
LATENCY_STAGES = ("estimate", "publish")


class MetricsError(RuntimeError):
    """The endpoint cannot start (package missing, address in use)."""


def _stable_copy(read: Callable[[], Mapping[str, Any]]) -> dict[str, Any]:
    # counters are written on the event loop while a scrape reads them from the HTTP thread:
    # a dict resized mid-copy raises RuntimeError, so copy again
    for _ in range(5):
        try:
            return dict(read())
        except RuntimeError:
            continue
    return {}


class MetricsServer:
    """Prometheus exposition of a daemon's health; ``start()``/``stop()``; ``port`` once started."""

    def __init__(self, counters: Callable[[], Mapping[str, int]], flags: Callable[[], Mapping[str, bool]],
                 uptime_s: Callable[[], float], n_cells: int, *, host: str = "127.0.0.1", port: int = 9464) -> None:
        try:
            from prometheus_client import CollectorRegistry, Histogram
        except ImportError as exc:
            raise MetricsError("metrics.enabled needs the prometheus-client package "
                               "(pip install 'socd[metrics]')") from exc
        self.host, self.requested_port = host, port
        self.port: int | None = None
        self._counters, self._flags, self._uptime, self._n = counters, flags, uptime_s, n_cells
        self.registry = CollectorRegistry(auto_describe=True)
        self.latency = Histogram("socd_latency_seconds", "frame timestamp to estimate / Zenoh publication",
                                 ["stage"], buckets=LATENCY_BUCKETS_S, registry=self.registry)
        for stage in LATENCY_STAGES:
            self.latency.labels(stage=stage)  # exported (as zero) before the first observation
        self.registry.register(self)
        self._server: Any = None
        self._thread: Any = None

    # -- prometheus_client collector protocol -------------------------------------------
    def describe(self) -> list:
        return []  # the families depend on what has been counted: collected at scrape time

    def collect(self) -> Iterator[Any]:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        events = CounterMetricFamily("socd_events", "daemon events by reason since start", labels=["reason"])
        for reason, n in sorted(_stable_copy(self._counters).items()):
            events.add_metric([reason], float(n))
        yield events
        flags = GaugeMetricFamily("socd_status_flag", "status word flags (1 = raised)", labels=["flag"])
        for flag, on in sorted(_stable_copy(self._flags).items()):
            flags.add_metric([flag], 1.0 if on else 0.0)
        yield flags
        yield GaugeMetricFamily("socd_uptime_seconds", "seconds since the daemon started", value=self._uptime())
        yield GaugeMetricFamily("socd_cells", "cells in the pack", value=float(self._n))

    # -- recording --------------------------------------------------------------------------
    def observe_latency(self, stage: str, seconds: float) -> None:
        if stage in LATENCY_STAGES and seconds >= 0:
            self.latency.labels(stage=stage).observe(seconds)

    def attach(self, health: Any) -> None:
        """Also feed every latency the :class:`~service.daemon.health.HealthMonitor` records."""
        record = health.record_latency

        def record_both(kind: str, seconds: float) -> None:
            record(kind, seconds)
            self.observe_latency(kind, seconds)

        health.record_latency = record_both

    # -- lifecycle -----------------------------------------------------------------------
    def start(self) -> int:
        from prometheus_client import start_http_server

        try:
            self._server, self._thread = start_http_server(self.requested_port, addr=self.host,
                                                           registry=self.registry)
        except OSError as exc:
            raise MetricsError(f"metrics: cannot listen on {self.host}:{self.requested_port}: "
                               f"{exc.strerror or exc}") from None
        self.port = int(self._server.server_port)
        log.info("metrics on http://%s:%d/metrics", self.host, self.port)
        return self.port

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            if self._thread is not None:
                self._thread.join(2.0)
            self._server = self._thread = None
