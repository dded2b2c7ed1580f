"""``[zenoh] config_file``: the user's Zenoh JSON5 file wins where it sets a key; the section's
mode/listen/connect/scouting fill the rest; a bad file is a config error naming it."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import pytest
import zenoh

from service.config import build_config, load_config
from service.daemon.zenoh_pub import ZenohConfigError, config_from_section, zenoh_config


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_file_keys_win_and_section_fills_the_rest(tmp_path: Path) -> None:
    file_port, section_port = _port(), _port()
    f = tmp_path / "zenoh.json5"
    f.write_text(f"""{{
  // the user's own Zenoh config: listens where it says, leaves scouting and connect alone
  listen: {{ endpoints: ["tcp/127.0.0.1:{file_port}"] }},
  transport: {{ unicast: {{ max_sessions: 7 }} }},
}}""")
    cfg = build_config({"zenoh": {"config_file": str(f), "listen": [f"tcp/127.0.0.1:{section_port}"],
                                  "connect": ["tcp/127.0.0.1:1"], "mode": "peer"}})
    z = config_from_section(cfg.zenoh)
    assert json.loads(z.get_json("listen/endpoints")) == [f"tcp/127.0.0.1:{file_port}"]  # the file's
    assert json.loads(z.get_json("transport/unicast/max_sessions")) == 7  # the file's own extra key
    assert json.loads(z.get_json("scouting/multicast/enabled")) is False  # ours: the file left it unset
    assert json.loads(z.get_json("connect/endpoints")) == ["tcp/127.0.0.1:1"]  # ours
    assert json.loads(z.get_json("mode")) == "peer"

    # the combined config opens a real session that listens where the file said
    cfg2 = build_config({"zenoh": {"config_file": str(f), "listen": [f"tcp/127.0.0.1:{section_port}"]}})
    server = zenoh.open(config_from_section(cfg2.zenoh))
    try:
        client = zenoh.open(zenoh_config("peer", [], [f"tcp/127.0.0.1:{file_port}"], False))
        try:
            deadline = time.monotonic() + 10
            while not list(server.info.peers_zid()) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert list(server.info.peers_zid()), "nobody connected to the file's listen endpoint"
        finally:
            client.close()
    finally:
        server.close()


def test_file_mode_and_scouting_win(tmp_path: Path) -> None:
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "client", scouting: { multicast: { enabled: false } }, '
                 'connect: { endpoints: ["tcp/127.0.0.1:7999"] } }')
    cfg = build_config({"zenoh": {"config_file": str(f), "mode": "peer", "connect": ["tcp/127.0.0.1:1"]}})
    z = config_from_section(cfg.zenoh)
    assert json.loads(z.get_json("mode")) == "client"
    assert json.loads(z.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7999"]


def test_relative_path_resolves_against_the_config_file(tmp_path: Path) -> None:
    (tmp_path / "conf").mkdir()
    (tmp_path / "conf" / "zenoh.json5").write_text("{}")
    toml = tmp_path / "conf" / "socd.toml"
    toml.write_text('[zenoh]\nconfig_file = "zenoh.json5"\n')
    cfg = load_config(toml, check_files=False)
    assert cfg.zenoh.config_file == tmp_path / "conf" / "zenoh.json5"
    assert json.loads(config_from_section(cfg.zenoh).get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]


@pytest.mark.parametrize("content", [None, "{ mode: "])
def test_missing_or_malformed_file_names_it(tmp_path: Path, content: str | None) -> None:
    f = tmp_path / "bad.json5"
    if content is not None:
        f.write_text(content)
    cfg = build_config({"zenoh": {"config_file": str(f)}})
    with pytest.raises(ZenohConfigError) as exc:
        config_from_section(cfg.zenoh)
    msg = str(exc.value)
    assert msg.startswith(f"zenoh.config_file: {f}: ") and "\n" not in msg


def test_docs_python_subscriber_runs_against_a_real_publisher() -> None:
    """The snippet in docs/zenoh.md, run as written (endpoint and wait shortened) on loopback."""
    import argparse
    import contextlib
    import io
    import re

    import numpy as np

    from service.daemon.health import HealthMonitor
    from service.daemon.zenoh_pub import PublishRound, ZenohPublisher

    doc = (Path(__file__).resolve().parent.parent / "docs" / "zenoh.md").read_text()
    code = re.search(r"```python\n(.*?)```", doc, re.DOTALL).group(1)
    port = _port()
    assert 'ENDPOINT = "tcp/127.0.0.1:7447"' in code and "time.sleep(30)" in code
    code = code.replace('ENDPOINT = "tcp/127.0.0.1:7447"', f'ENDPOINT = "tcp/127.0.0.1:{port}"')
    code = code.replace("time.sleep(30)", "_wait_for_samples()")

    section = argparse.Namespace(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], connect=[], scouting_multicast=False,
                                 key_prefix="bms", pack_id="pack0", config_file=None)
    health = HealthMonitor()
    pub = ZenohPublisher(section, 8, health)

    def round_() -> PublishRound:
        return PublishRound(t_s=1.0, soc=np.array([0.5, 0.6]), soc_std=np.array([0.01, 0.02]),
                            voltage_v=np.array([3.6, 3.7]), stale=np.zeros(2, bool), params={},
                            health=health.payload(1.0), status_flags={})

    out = io.StringIO()

    def _wait_for_samples() -> None:
        deadline = time.monotonic() + 10
        while out.getvalue().count("cell/") < 2 and time.monotonic() < deadline:
            pub.submit(round_())
            time.sleep(0.1)

    pub.start()
    try:
        pub.submit(round_())
        deadline = time.monotonic() + 10
        while pub.rounds_published < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        with contextlib.redirect_stdout(out):
            exec(compile(code, "docs/zenoh.md", "exec"), {"_wait_for_samples": _wait_for_samples})
    finally:
        pub.stop()
    text = out.getvalue()
    assert "pack SOC mean 55.0 %" in text
    assert "bms/pack0/cell/0/soc 50.0 ± 1.0 %" in text and "bms/pack0/cell/1/soc 60.0 ± 2.0 %" in text
