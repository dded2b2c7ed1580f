"""Zenoh helpers shared by the publisher tests: a free loopback port and a session on
loopback with multicast scouting off (DESIGN §5: every test config)."""

from __future__ import annotations

import socket

import zenoh

from service.daemon.zenoh_pub import zenoh_config


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def loopback_session(mode: str = "peer", listen: list[str] | None = None, connect: list[str] | None = None):
    return zenoh.open(zenoh_config(mode, listen or [], connect or [], scouting_multicast=False))
