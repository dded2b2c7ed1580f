"""Smoke tests of python-can's real ``socketcan`` interface on ``vcan0``.

They skip on a host without kernel CAN; CI runs them in the VM that
``.ci/vcan_vm.sh`` boots (``bash .ci/vcan_vm.sh``).
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from collections.abc import Iterator

import can
import pytest
from vcan_support import VCAN_CHANNEL, requires_vcan, vcan_supports_fd

pytestmark = [pytest.mark.vcan, requires_vcan]

# CAN FD payload lengths: a few classic ones and every FD-only one (12..64).
FD_LENGTHS = (0, 1, 5, 8, 12, 16, 20, 24, 32, 48, 64)
RECV_TIMEOUT_S = 5.0
# A child interpreter's first import is slow under the VM's software emulation.
CHILD_START_TIMEOUT_S = 180.0
PROCESS_FRAMES = 500


def _socketcan_bus(fd: bool = False) -> can.BusABC:
    return can.Bus(interface="socketcan", channel=VCAN_CHANNEL, fd=fd)


@pytest.fixture
def bus_pair(request: pytest.FixtureRequest) -> Iterator[tuple[can.BusABC, can.BusABC]]:
    fd = getattr(request, "param", False)
    if fd and not vcan_supports_fd():
        pytest.skip(
            f"{VCAN_CHANNEL} mtu is not 72: no CAN FD (`ip link set {VCAN_CHANNEL} mtu 72`)"
        )
    with _socketcan_bus(fd) as tx, _socketcan_bus(fd) as rx:
        yield tx, rx


def _classic_frames() -> list[can.Message]:
    frames = []
    for i in range(64):
        extended = i % 2 == 1
        arbitration_id = (0x1ABC0000 + i * 0x1111) if extended else (0x100 + i * 0x17) & 0x7FF
        length = i % 9
        frames.append(
            can.Message(
                arbitration_id=arbitration_id,
                is_extended_id=extended,
                data=bytes((i + k) & 0xFF for k in range(length)),
            )
        )
    frames.append(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b""))
    frames.append(can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True, data=b"\xff" * 8))
    frames.append(can.Message(arbitration_id=0x123, is_remote_frame=True, dlc=4))
    return frames


def _fd_frames() -> list[can.Message]:
    frames = []
    for i, length in enumerate(FD_LENGTHS * 2):
        extended = i % 2 == 0
        frames.append(
            can.Message(
                arbitration_id=(0x18DA0000 + i) if extended else 0x200 + i,
                is_extended_id=extended,
                is_fd=True,
                bitrate_switch=i % 3 != 0,
                data=bytes((0xA5 ^ k ^ i) & 0xFF for k in range(length)),
            )
        )
    return frames


def _summary(msg: can.Message) -> tuple:
    return (
        msg.arbitration_id,
        msg.is_extended_id,
        msg.is_remote_frame,
        msg.is_fd,
        msg.is_fd and msg.bitrate_switch,
        msg.dlc,
        b"" if msg.is_remote_frame else bytes(msg.data),  # an RTR frame carries no payload
    )


def _send_batch_receive_all(
    tx: can.BusABC, rx: can.BusABC, frames: list[can.Message]
) -> list[can.Message]:
    for msg in frames:
        tx.send(msg, timeout=1.0)
    received = []
    for _ in frames:
        msg = rx.recv(timeout=RECV_TIMEOUT_S)
        assert msg is not None, f"only {len(received)} of {len(frames)} frames arrived"
        received.append(msg)
    return received


def test_classic_frames_arrive_in_order(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = bus_pair
    frames = _classic_frames()

    received = _send_batch_receive_all(tx, rx, frames)

    assert [_summary(m) for m in received] == [_summary(m) for m in frames]
    assert all(m.channel == VCAN_CHANNEL and not m.is_error_frame for m in received)
    assert all(b.timestamp >= a.timestamp for a, b in itertools.pairwise(received))
    assert rx.recv(timeout=0.2) is None, "a frame arrived that was never sent"


@pytest.mark.parametrize("bus_pair", [True], indirect=True, ids=["fd"])
def test_fd_frames_arrive_in_order(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = bus_pair
    frames = _fd_frames() + _classic_frames()[:8]  # an FD socket also carries classic frames

    received = _send_batch_receive_all(tx, rx, frames)

    assert [_summary(m) for m in received] == [_summary(m) for m in frames]
    assert rx.recv(timeout=0.2) is None, "a frame arrived that was never sent"


# The child paces itself (a pause after every burst) so the parent's receive
# queue never overflows, and retries a send the kernel refuses with ENOBUFS.
# Blocking asammdf cuts the child's start-up under the VM from about a minute
# to seconds; python-can then just reports MF4 as unavailable.
_SENDER = """
import errno, sys, time
sys.modules["asammdf"] = None  # no MF4 needed: skips python-can's slowest optional import
import can

channel, count = sys.argv[1], int(sys.argv[2])
with can.Bus(interface="socketcan", channel=channel) as bus:
    for seq in range(count):
        msg = can.Message(
            arbitration_id=(0x10000 + seq) if seq % 2 else 0x300 + seq % 0x100,
            is_extended_id=bool(seq % 2),
            data=seq.to_bytes(4, "little") + bytes([seq % 251, 0x5A]),
        )
        for attempt in range(200):
            try:
                bus.send(msg, timeout=1.0)
                break
            except can.CanOperationError as error:
                if error.error_code != errno.ENOBUFS:
                    raise
                time.sleep(0.002)
        else:
            sys.exit(f"frame {seq}: ENOBUFS 200 times")
        if seq % 10 == 9:
            time.sleep(0.01)
"""


def test_frames_cross_processes() -> None:
    # The receiver is bound before the sender starts, so no frame can be missed.
    with (
        _socketcan_bus() as rx,
        subprocess.Popen(
            [sys.executable, "-c", _SENDER, VCAN_CHANNEL, str(PROCESS_FRAMES)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        ) as sender,
    ):
        try:
            received = _receive_from(rx, sender, PROCESS_FRAMES)
            output, _ = sender.communicate(timeout=60)
        finally:
            sender.kill()  # no-op once it has exited; else Popen's exit would wait forever
    assert sender.returncode == 0, f"sender failed:\n{output}"

    sequence = [int.from_bytes(m.data[:4], "little") for m in received]
    assert sequence == list(range(PROCESS_FRAMES))
    for seq, msg in zip(sequence, received):
        assert msg.is_extended_id == bool(seq % 2)
        assert msg.arbitration_id == ((0x10000 + seq) if seq % 2 else 0x300 + seq % 0x100)
        assert bytes(msg.data[4:]) == bytes([seq % 251, 0x5A])


def _receive_from(rx: can.BusABC, sender: subprocess.Popen, count: int) -> list[can.Message]:
    """Receive ``count`` frames; wait long for the first (child start-up), then briefly."""
    received: list[can.Message] = []
    deadline = time.monotonic() + CHILD_START_TIMEOUT_S
    while len(received) < count and time.monotonic() < deadline:
        msg = rx.recv(timeout=0.5)
        if msg is not None:
            received.append(msg)
            deadline = time.monotonic() + RECV_TIMEOUT_S
        elif sender.poll() not in (None, 0):
            output = sender.stdout.read() if sender.stdout else ""
            pytest.fail(f"sender exited with {sender.returncode}:\n{output}")
    assert len(received) == count, f"{len(received)} of {count} frames arrived"
    return received
