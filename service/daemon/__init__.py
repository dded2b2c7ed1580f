"""The online service: CAN receive path, estimation loop, Zenoh publication, checkpoints, health.

:class:`service.daemon.daemon.Daemon` wires the parts; each module owns one seam:

- :mod:`~service.daemon.can_rx`: python-can receive path that never loses an error, with
  reconnect and exponential backoff;
- :mod:`~service.daemon.zenoh_pub`: Zenoh session, publishers and the snapshot queryable,
  behind a bounded drop-oldest queue so publication never blocks estimation;
- :mod:`~service.daemon.checkpoint`: atomic, checksummed estimator checkpoints;
- :mod:`~service.daemon.health`: counters by reason, latency percentiles, status flags;
- :mod:`~service.daemon.payloads`: the JSON wire format (pydantic, versioned).
"""
