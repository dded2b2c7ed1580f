"""``socd replay`` and ``socd run`` as two separate processes over a real SocketCAN vcan0.

Skips where the kernel has no CAN (the CI host); CI runs it inside the VM of
``.ci/vcan_vm.sh``.  Replay is real time: a kernel bus stamps frames on arrival,
so a faster replay would compress the time steps the daemon integrates.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import cantools
import pytest

from vcan_support import VCAN_CHANNEL, requires_vcan

pytestmark = [pytest.mark.vcan, requires_vcan]

REPO = Path(__file__).resolve().parents[1]
RECORDING = REPO / "service" / "data" / "pan18650pf_25C_US06.csv"
N_CELLS = 8
REPLAY_S = 40


def _config(tmp_path: Path) -> Path:
    cfg = tmp_path / "vcan.toml"
    cfg.write_text(
        f"""
cell_profile = "{REPO / 'configs/cells/panasonic_18650pf.toml'}"
[bus]
interface = "socketcan"
channel = "{VCAN_CHANNEL}"
[dbc]
input = "{REPO / 'dbc/bms_pack.dbc'}"
output = "{REPO / 'dbc/socd_output.dbc'}"
[pack]
n_cells = {N_CELLS}
[mapping]
current_signal = "BMS_PackCurrent"
current_sign = -1.0
cell_voltage_pattern = "BMS_Cell{{number:03d}}_V"
temperature_pattern = "BMS_Temp{{number:02d}}_C"
cells_per_sensor = 4
[output]
can_period_s = 0.5
zenoh_enabled = false
[checkpoint]
path = "{tmp_path / 'state.ckpt'}"
interval_s = 5.0
"""
    )
    return cfg


def _wait_for_line(proc: subprocess.Popen, needle: str, timeout_s: float) -> str:
    """Read the process's stderr until a line contains ``needle`` (readiness, never sleep)."""
    deadline = time.monotonic() + timeout_s
    seen = []
    assert proc.stderr is not None
    os.set_blocking(proc.stderr.fileno(), False)
    buf = b""
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            break
        chunk = proc.stderr.read()
        if chunk:
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for line in lines:
                text = line.decode(errors="replace")
                seen.append(text)
                if needle in text:
                    return text
        else:
            time.sleep(0.05)
    raise AssertionError(f"no line containing {needle!r} within {timeout_s} s; stderr so far:\n" + "\n".join(seen))


def test_replay_and_daemon_as_processes_over_vcan0(tmp_path: Path) -> None:
    cfg = _config(tmp_path)
    out_db = cantools.database.load_file(REPO / "dbc" / "socd_output.dbc")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    listener = can.Bus(interface="socketcan", channel=VCAN_CHANNEL)
    daemon = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "run", "--config", str(cfg), "--log-level", "info"],
        cwd=REPO, env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
    )
    try:
        _wait_for_line(daemon, "socd running", timeout_s=240)  # logged once the bus is open
        replay = subprocess.run(
            [sys.executable, "-m", "service.cli", "replay", str(RECORDING), "--config", str(cfg),
             "-i", "socketcan", "-c", VCAN_CHANNEL, "--cells", str(N_CELLS), "--speed", "1",
             "--stop", str(REPLAY_S), "--quiet"],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=300,
        )
        assert replay.returncode == 0, replay.stderr
        soc: dict[int, float] = {}
        status_seen = False
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (len(soc) == N_CELLS and status_seen):
            msg = listener.recv(timeout=1.0)
            if msg is None or not msg.is_extended_id:
                continue
            try:
                m = out_db.get_message_by_frame_id(msg.arbitration_id)
            except KeyError:
                continue
            values = m.decode(msg.data, decode_choices=False)
            if m.name == "SOCD_CellSoc":
                soc[int(values["SOCD_SocCellIndex"])] = float(values["SOCD_Soc"])
            elif m.name == "SOCD_Status":
                status_seen = True
        assert status_seen, "no SOCD_Status frame from the daemon"
        assert sorted(soc) == list(range(N_CELLS)), f"SOC frames for cells {sorted(soc)}"
        # the drive starts fully charged: an OCV start lands high, 40 s of US06 moves it little
        assert all(70.0 <= v <= 100.0 for v in soc.values()), soc
    finally:
        daemon.send_signal(signal.SIGTERM)
        try:
            rc = daemon.wait(timeout=60)
        finally:
            if daemon.poll() is None:
                daemon.kill()
            listener.shutdown()
    assert rc == 0, f"daemon exit status {rc} after SIGTERM"
    assert (tmp_path / "state.ckpt").is_file(), "no checkpoint written on SIGTERM"
