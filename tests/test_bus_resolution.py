"""Which bus ``socd run`` / ``socd replay`` open: flags > the user's config > python-can's own
configuration (CAN_INTERFACE/CAN_CHANNEL, ~/.canrc) > the bundled default; giving up after
``max_open_retries``; an unknown interface is a config error at once; replay warns on the
in-process virtual bus and plays .gz logs."""

from __future__ import annotations

import argparse
import gzip
import shutil
import threading
import time
from pathlib import Path

import can
import pytest

from service.bus.cli_args import BusConfigError, add_bus_arguments, resolve_bus
from service.cli import main
from service.config import build_config, load_config

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "configs" / "default.toml"


@pytest.fixture(autouse=True)
def clean_python_can_config(monkeypatch, tmp_path):
    """No CAN_* variables and an empty home, so only what a test sets is python-can's config."""
    for var in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(var, raising=False)
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    return home


def _ns(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_bus_arguments(p)
    return p.parse_args(list(argv))


def _user_config(tmp_path: Path, bus: str) -> Path:
    text = DEFAULT.read_text().replace("cell_profile = \"cells/", f"cell_profile = \"{ROOT}/configs/cells/")
    text = text.replace('"../dbc/', f'"{ROOT}/dbc/')
    start = text.index("[bus]")
    end = text.index("[dbc]")
    path = tmp_path / "user.toml"
    path.write_text(text[:start] + bus + "\n" + text[end:])
    return path


def test_precedence_flag_over_config_over_python_can(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.setenv("CAN_CHANNEL", "from_env")
    user = load_config(_user_config(tmp_path, '[bus]\ninterface = "virtual"\nchannel = "from_config"\n'))
    bundled = load_config(DEFAULT)

    # flags win over everything
    r = resolve_bus(_ns("-i", "virtual", "-c", "from_flag"), user, user_config=True)
    assert (r.bus.interface, r.bus.channel, r.interface_from) == ("virtual", "from_flag", "command line")
    # the user's config wins over python-can's environment
    r = resolve_bus(_ns(), user, user_config=True)
    assert (r.bus.interface, r.bus.channel, r.channel_from) == ("virtual", "from_config", "config")
    # with only the bundled default, python-can's environment wins over it
    r = resolve_bus(_ns(), bundled, user_config=False)
    assert (r.bus.interface, r.bus.channel) == ("udp_multicast", "from_env")
    assert r.interface_from == "python-can config"
    assert "preserve_timestamps" not in r.kwargs()  # the bundled virtual bus's own setting does not carry over
    # a flag for one setting, python-can for the other
    r = resolve_bus(_ns("-c", "flag_channel"), bundled, user_config=False)
    assert (r.bus.interface, r.bus.channel) == ("udp_multicast", "flag_channel")


def test_python_can_config_file_is_read(clean_python_can_config) -> None:
    (clean_python_can_config / ".canrc").write_text("[default]\ninterface = virtual\nchannel = from_canrc\n")
    r = resolve_bus(_ns(), load_config(DEFAULT), user_config=False)
    assert (r.bus.interface, r.bus.channel, r.channel_from) == ("virtual", "from_canrc", "python-can config")


def test_nothing_anywhere_is_the_bundled_default() -> None:
    r = resolve_bus(_ns(), load_config(DEFAULT), user_config=False)
    assert (r.bus.interface, r.bus.channel, r.interface_from) == ("virtual", "vcan0", "default")
    assert r.kwargs()["preserve_timestamps"] is True


def test_socd_env_counts_as_the_users_config(monkeypatch) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.setenv("SOCD_BUS__INTERFACE", "virtual")
    monkeypatch.setenv("SOCD_BUS__CHANNEL", "socd_env")
    r = resolve_bus(_ns(), load_config(DEFAULT), user_config=False)
    assert (r.bus.interface, r.bus.channel) == ("virtual", "socd_env")


def test_unknown_interfaces_are_config_errors(monkeypatch, tmp_path, capsys) -> None:
    cfg = build_config({"bus": {"interface": "no_such_bus"}})
    with pytest.raises(BusConfigError, match="bus.interface: unknown python-can interface 'no_such_bus'"):
        resolve_bus(_ns(), cfg)
    monkeypatch.setenv("CAN_INTERFACE", "warp_drive")
    with pytest.raises(BusConfigError, match="warp_drive"):
        resolve_bus(_ns(), load_config(DEFAULT), user_config=False)
    # socd run: exit 2 at once, naming the field, nothing started
    path = _user_config(tmp_path, '[bus]\ninterface = "no_such_bus"\n')
    t0 = time.monotonic()
    assert main(["run", "--config", str(path)]) == 2
    assert time.monotonic() - t0 < 10
    err = capsys.readouterr().err
    assert "bus.interface: unknown python-can interface 'no_such_bus'" in err


def _run_config(tmp_path: Path, bus: str) -> Path:
    """A user config on ``bus`` with CAN and Zenoh output off and the checkpoint in tmp_path."""
    path = _user_config(tmp_path, bus)
    text = path.read_text()
    text = text.replace("can_enabled = true", "can_enabled = false").replace("zenoh_enabled = true",
                                                                          "zenoh_enabled = false")
    text = text.replace("[checkpoint]\n", f'[checkpoint]\npath = "{tmp_path / "state.npz"}"\n')
    path.write_text(text)
    return path


def test_run_gives_up_after_max_bus_retries(tmp_path, capsys) -> None:
    # a SocketCAN interface that does not exist fails to open on every host (no AF_CAN, or ENODEV)
    path = _run_config(tmp_path, '[bus]\ninterface = "socketcan"\nchannel = "socd_no_such_if0"\n'
                                 'reconnect_initial_s = 0.05\nreconnect_max_s = 0.1\nmax_open_retries = 50\n')
    t0 = time.monotonic()
    rc = main(["run", "--config", str(path), "--max-bus-retries", "2", "--log-level", "error"])
    assert rc == 1
    assert time.monotonic() - t0 < 20
    err = capsys.readouterr().err
    assert "cannot open CAN bus socketcan:socd_no_such_if0 after 3 attempts" in err
    assert "giving up" in err


def test_run_retries_a_backend_that_raises_its_own_kind_of_error(tmp_path, capsys) -> None:
    """python-can's socketcand backend without host and port raises TypeError (a vendor backend
    without its library, NameError): a failed open like any other, retried and given up on in one
    line, not a traceback."""
    path = _run_config(tmp_path, '[bus]\ninterface = "socketcand"\nchannel = "127.0.0.1"\n'
                                 'reconnect_initial_s = 0.05\nreconnect_max_s = 0.1\n')
    rc = main(["run", "--config", str(path), "--max-bus-retries", "1", "--log-level", "error"])
    err = capsys.readouterr().err
    assert rc == 1 and "Traceback" not in err, err
    assert "cannot open CAN bus socketcand:127.0.0.1 after 2 attempts" in err and "host" in err, err


def test_run_flags_override_the_config_bus(tmp_path, capsys) -> None:
    path = _run_config(tmp_path, '[bus]\ninterface = "virtual"\nchannel = "cfg"\n'
                                 'reconnect_initial_s = 0.05\nreconnect_max_s = 0.1\n')
    rc = main(["run", "--config", str(path), "-i", "socketcan", "-c", "socd_no_such_if1", "--max-bus-retries", "1",
               "--log-level", "error"])
    assert rc == 1
    assert "socketcan:socd_no_such_if1 after 2 attempts" in capsys.readouterr().err


# -- replay -------------------------------------------------------------------------------
def _small_log(tmp_path: Path, n: int = 12) -> Path:
    path = tmp_path / "frames.log"
    with can.Logger(path) as log:
        for k in range(n):
            log.on_message_received(can.Message(timestamp=100.0 + 0.01 * k, arbitration_id=0x100 + k,
                                                data=bytes([k] * 8), is_extended_id=False))
    return path


def test_replay_warns_on_the_in_process_virtual_bus(tmp_path, capsys) -> None:
    log = _small_log(tmp_path)
    assert main(["replay", str(log), "--fast", "-q"]) == 0
    err = capsys.readouterr().err
    assert "warning: sending to python-can's in-process 'virtual' bus" in err and "12 frames sent" in err


def test_replay_honours_python_can_environment(monkeypatch, tmp_path, capsys) -> None:
    """CAN_INTERFACE/CAN_CHANNEL choose the bus when neither flag nor --config does."""
    log = _small_log(tmp_path)
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "socd_env_channel")
    got: list[can.Message] = []
    with can.Bus(interface="virtual", channel="socd_env_channel") as rx:
        done = threading.Event()

        def drain() -> None:
            while not done.is_set():
                m = rx.recv(0.05)
                if m is not None:
                    got.append(m)

        t = threading.Thread(target=drain)
        t.start()
        try:
            assert main(["replay", str(log), "--fast", "-q"]) == 0
            deadline = time.monotonic() + 5
            while len(got) < 12 and time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            done.set()
            t.join()
    assert [m.arbitration_id for m in got] == [0x100 + k for k in range(12)]
    err = capsys.readouterr().err
    assert "virtual:socd_env_channel (python-can config)" in err


def test_replay_plays_gzip_logs(tmp_path, capsys) -> None:
    log = _small_log(tmp_path, n=7)
    gz = tmp_path / "frames.log.gz"
    with log.open("rb") as src, gzip.open(gz, "wb") as dst:
        shutil.copyfileobj(src, dst)
    dotted = tmp_path / "drive.2024-01-01.log.gz"
    shutil.copy(gz, dotted)  # more dots than python-can's LogReader looks at
    rec = tmp_path / "copy.asc"
    assert main(["replay", str(gz), "--record", str(rec), "-q"]) == 0
    assert len(list(can.LogReader(rec))) == 7
    assert main(["replay", str(dotted), "--no-send", "--record", str(tmp_path / "copy2.asc"), "-q"]) == 0
    assert "7 frames recorded to" in capsys.readouterr().err  # no bus was opened: nothing was sent
    bad = tmp_path / "frames.txt.gz"
    shutil.copy(gz, bad)
    assert main(["replay", str(bad), "--no-send"]) == 2


def test_opener_limits_start_up_only() -> None:
    """The retry limit is for a bus that never opened; one that opened once is reopened for ever."""
    from service.config import BusConfig
    from service.daemon.bus_open import BusOpener, BusUnavailable

    missing = BusConfig(interface="socketcan", channel="socd_no_such_if2", max_open_retries=2)
    opener = BusOpener(missing)
    for _ in range(2):
        with pytest.raises((can.CanError, OSError)):
            opener()
    with pytest.raises(BusUnavailable, match="socketcan:socd_no_such_if2 after 3 attempts"):
        opener()

    opener = BusOpener(BusConfig(interface="virtual", channel="socd_opener", max_open_retries=2))
    opener().shutdown()  # opened once
    opener.kwargs = missing.bus_kwargs()  # ... then the link goes away
    for _ in range(6):
        with pytest.raises((can.CanError, OSError)):
            opener()
    assert opener.failures == 6


def test_run_on_the_default_virtual_bus_warns(tmp_path, capsys) -> None:
    """socd run with nothing set listens on the in-process virtual bus: it says so (and stops on SIGINT)."""
    import signal

    path = _run_config(tmp_path, "")
    timer = threading.Timer(1.5, lambda: signal.raise_signal(signal.SIGINT))
    timer.start()
    try:
        assert main(["run", "--config", str(path), "--log-level", "error"]) == 0
    finally:
        timer.cancel()
    assert "warning: listening on python-can's in-process 'virtual' bus virtual:vcan0" in capsys.readouterr().err
