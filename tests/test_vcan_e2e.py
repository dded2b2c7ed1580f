"""``socd replay`` and ``socd run`` as two separate processes over a real SocketCAN vcan0.

Skips where the kernel has no CAN (the CI host); CI runs it inside the VM of
``.ci/vcan_vm.sh``, where every Python process costs tens of seconds of start-up, so one
daemon and one replay carry all the checks.  A kernel bus stamps frames on arrival: the
replay runs at 20x with the sample time in ``BMS_TimeSync`` (``mapping.time_signal``); the
daemon's output frames are decoded with cantools from the shipped output DBC, its SIGTERM
checkpoint is restored, and its SOC is compared with an in-process replay's.
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
import numpy as np
import pytest
from daemon_support import run_daemon
from vcan_support import VCAN_CHANNEL, requires_vcan

pytestmark = [pytest.mark.vcan, requires_vcan]

REPO = Path(__file__).resolve().parents[1]
RECORDING = REPO / "service" / "data" / "pan18650pf_25C_US06.csv"
N_CELLS = 8
SYNC_SPEED = 20
SYNC_REPLAY_S = 150
#: resolution of ``SOCD_Soc`` in the output DBC, %
SOC_FRAME_RESOLUTION_PCT = 0.01


def _write_config(path: Path, *, interface: str, channel: str, output: str, checkpoint: Path,
                  checkpoint_interval_s: float, time_signal: str | None = None) -> Path:
    """A daemon config on the shipped DBCs and the bundled Panasonic profile, ``N_CELLS`` cells."""
    path.write_text(
        f"""
cell_profile = "{REPO / 'configs/cells/panasonic_18650pf.toml'}"
[bus]
interface = "{interface}"
channel = "{channel}"
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
{f'time_signal = "{time_signal}"' if time_signal else ""}
[output]
{output}
[checkpoint]
path = "{checkpoint}"
interval_s = {checkpoint_interval_s}
"""
    )
    return path


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


def _checkpoint_t_s(path: Path) -> float | None:
    from service.daemon.checkpoint import decode_checkpoint

    try:
        res = decode_checkpoint(path.read_bytes(), str(path))
    except OSError:
        return None
    t = res.meta.get("t_s") if res.ok else None
    return float(t) if isinstance(t, (int, float)) else None


def _published_soc(listener: can.BusABC, timeout_s: float) -> tuple[dict[int, float], bool]:
    """The daemon's output frames read from ``listener`` after its backlog (the replay's own
    frames) is drained: the last ``SOCD_Soc`` per cell (%) and whether ``SOCD_Status`` came."""
    out_db = cantools.database.load_file(REPO / "dbc" / "socd_output.dbc")
    while listener.recv(timeout=0.0) is not None:
        pass
    soc: dict[int, float] = {}
    status_seen = False
    deadline = time.monotonic() + timeout_s
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
    return soc, status_seen


def _config(tmp_path: Path, time_signal: str | None, interface: str, channel: str, tag: str, output: str) -> Path:
    return _write_config(tmp_path / f"{tag}.toml", interface=interface, channel=channel, output=output,
                         checkpoint=tmp_path / f"{tag}.ckpt", checkpoint_interval_s=1.0, time_signal=time_signal)


def test_replay_at_20x_over_vcan0_publishes_and_gives_the_in_process_soc(tmp_path: Path) -> None:
    from replay.pack import pack_frames
    from service.cell.profile import load_profile
    from service.config import load_config
    from service.daemon.daemon import Daemon
    from service.recording import load_recording

    cfg = _config(tmp_path, "BMS_SampleTime", "socketcan", VCAN_CHANNEL, "vcan",
                  "can_period_s = 0.5\nzenoh_enabled = false")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    listener = can.Bus(interface="socketcan", channel=VCAN_CHANNEL)
    daemon = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "run", "--config", str(cfg), "--log-level", "info"],
        cwd=REPO, env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
    )
    ckpt = tmp_path / "vcan.ckpt"
    last_t = float(SYNC_REPLAY_S - 1)  # the recording is sampled at 1 s; --stop keeps t < SYNC_REPLAY_S
    try:
        _wait_for_line(daemon, "clock BMS_SampleTime", timeout_s=240)  # logged once the bus is open
        replay = subprocess.run(
            [sys.executable, "-m", "service.cli", "replay", str(RECORDING), "--config", str(cfg),
             "-i", "socketcan", "-c", VCAN_CHANNEL, "--cells", str(N_CELLS), "--soc0", "1.0",
             "--speed", str(SYNC_SPEED), "--stop", str(SYNC_REPLAY_S), "--quiet"],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=600, check=False,
        )
        assert replay.returncode == 0, replay.stderr
        # ready when a periodic checkpoint holds the last sample (readiness, not a sleep)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and _checkpoint_t_s(ckpt) != last_t:
            assert daemon.poll() is None, "the daemon exited"
            time.sleep(0.2)
        assert _checkpoint_t_s(ckpt) == last_t, f"checkpoint at t={_checkpoint_t_s(ckpt)}, not {last_t}"
        published, status_seen = _published_soc(listener, timeout_s=30)
    finally:
        daemon.send_signal(signal.SIGTERM)
        try:
            rc = daemon.wait(timeout=60)
        finally:
            if daemon.poll() is None:
                daemon.kill()
            listener.shutdown()
    assert rc == 0, f"daemon exit status {rc} after SIGTERM"
    assert _checkpoint_t_s(ckpt) == last_t, "the SIGTERM checkpoint does not hold the last sample"
    vcan_config = load_config(cfg)
    bus = can.Bus(interface="virtual", channel=f"ckpt-{time.monotonic_ns()}")
    try:  # the daemon's final state, as a restart would restore it
        restored = Daemon(vcan_config, bus, install_signal_handlers=False)
        assert restored.restore() == "restored"
        soc_vcan = np.array(restored.estimator.soc)
    finally:
        bus.shutdown()

    # what the daemon published on the bus is its final estimate, at the frame's resolution
    assert status_seen, "no SOCD_Status frame from the daemon"
    assert sorted(published) == list(range(N_CELLS)), f"SOC frames for cells {sorted(published)}"
    frame_soc = np.array([published[c] for c in range(N_CELLS)])
    assert np.max(np.abs(frame_soc - 100 * soc_vcan)) <= SOC_FRAME_RESOLUTION_PCT, (frame_soc, 100 * soc_vcan)

    # the in-process replay of the same frames: python-can's virtual bus keeps the sender's stamps
    ref_cfg = load_config(_config(tmp_path, None, "virtual", f"ref-{time.monotonic_ns()}", "ref",
                                  "can_enabled = false\nzenoh_enabled = false"))
    rec = load_recording(RECORDING).slice(0, SYNC_REPLAY_S)
    frames, pack = pack_frames(rec, ref_cfg, load_profile(ref_cfg.cell_profile), N_CELLS, start_soc=1.0)
    ref = run_daemon(ref_cfg, frames)
    assert ref.steps == len(pack) - 1
    diff_pct = 100 * float(np.max(np.abs(soc_vcan - ref.estimator.soc)))
    print(f"\nSOC, {SYNC_SPEED}x replay over {VCAN_CHANNEL} with time sync vs in-process: max |diff| {diff_pct:.2e} %")
    assert float(np.min(pack.truth_soc[0] - pack.truth_soc[-1])) > 0.02, "the drive moved the SOC too little"
    assert diff_pct < 0.1
