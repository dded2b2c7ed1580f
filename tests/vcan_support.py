"""Skip logic for tests that need a real SocketCAN ``vcan0``.

The CI host kernel has no CAN support (``socket(AF_CAN, ...)`` fails with
errno 97), so tests marked ``vcan`` skip there and run inside the small VM
that ``.ci/vcan_vm.sh`` boots with ``vcan0`` up (mtu 72, so CAN FD works).

Reuse in a test module::

    import pytest
    from vcan_support import VCAN_CHANNEL, requires_vcan

    pytestmark = [pytest.mark.vcan, requires_vcan]

or take the ``vcan_channel`` fixture (re-export it from the test module or a
conftest), which skips with the same reason and returns the channel name.
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

VCAN_CHANNEL = "vcan0"
CANFD_MTU = 72  # sizeof(struct canfd_frame); a classic-only link has mtu 16
_IFF_UP = 0x1
_HINT = "run inside .ci/vcan_vm.sh"


def vcan_unavailable_reason(channel: str = VCAN_CHANNEL) -> str | None:
    """Why SocketCAN on ``channel`` cannot be used here, or None if it can."""
    af_can = getattr(socket, "AF_CAN", None)
    if af_can is None:
        return f"no kernel CAN (this Python has no socket.AF_CAN): {_HINT}"
    try:
        sock = socket.socket(af_can, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as error:
        return f"no kernel CAN (AF_CAN unavailable: {error.strerror}): {_HINT}"
    with sock:
        try:
            sock.bind((channel,))
        except OSError as error:
            return f"no {channel} interface ({error.strerror}): {_HINT}"
    if not _link_flags(channel) & _IFF_UP:
        return f"{channel} exists but is down: `ip link set up {channel}`"
    return None


def vcan_available(channel: str = VCAN_CHANNEL) -> bool:
    """True where a raw CAN socket can be bound to ``channel`` and the link is up."""
    return vcan_unavailable_reason(channel) is None


def vcan_supports_fd(channel: str = VCAN_CHANNEL) -> bool:
    """True if ``channel`` carries CAN FD frames (its mtu is 72, not 16)."""
    try:
        return int(_sysfs_net(channel, "mtu")) >= CANFD_MTU
    except (OSError, ValueError):
        return False


def _link_flags(channel: str) -> int:
    try:
        return int(_sysfs_net(channel, "flags"), 16)
    except (OSError, ValueError):
        return 0


def _sysfs_net(channel: str, attribute: str) -> str:
    return (Path("/sys/class/net") / channel / attribute).read_text().strip()


_REASON = vcan_unavailable_reason()

#: Marker: skip the test unless ``vcan0`` is usable (checked once, at import).
requires_vcan = pytest.mark.skipif(_REASON is not None, reason=_REASON or "")


@pytest.fixture
def vcan_channel() -> str:
    """The SocketCAN channel name; skips the test where it is not usable."""
    reason = vcan_unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    return VCAN_CHANNEL
