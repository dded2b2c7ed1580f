"""What an installed socd finds without the repository: its packaged DBCs, configs and cell
profiles, the fallback of a copied config to them, the checkpoint's default place, the one-line
errors for a missing extra, and the deployment files (systemd unit, Dockerfile)."""

from __future__ import annotations

import importlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from service import assets
from service.config import (
    DEFAULT_CELL_PROFILE,
    DEFAULT_CONFIG,
    DEFAULT_INPUT_DBC,
    ConfigError,
    default_checkpoint_path,
    load_config,
)
from service.extras import EXTRA_OF_MODULE, install_hint, missing_extra

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    for k in list(os.environ):
        if k.upper().startswith("SOCD_") or k == "STATE_DIRECTORY":
            monkeypatch.delenv(k)


def test_packaged_assets_are_the_repository_files():
    # one copy of each file: the package's asset directories are the top-level dbc/ and configs/
    for name in ("bms_pack.dbc", "socd_output.dbc"):
        assert assets.dbc_path(name).read_bytes() == (ROOT / "dbc" / name).read_bytes()
    assert DEFAULT_CELL_PROFILE.samefile(ROOT / "configs" / "cells" / "panasonic_18650pf.toml")
    assert DEFAULT_CONFIG.samefile(ROOT / "configs" / "default.toml")
    assert {"default.toml", "socketcan_can0.toml", "vcan0.toml"} <= set(assets.example_configs())


def test_example_config_copied_elsewhere_falls_back_to_packaged_files(tmp_path, monkeypatch):
    # the systemd recipe: the example config alone in /etc/socd, its ../dbc and cells/ absent
    etc = tmp_path / "etc" / "socd"
    etc.mkdir(parents=True)
    shutil.copy(ROOT / "configs" / "socketcan_can0.toml", etc / "socd.toml")
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "state"))
    cfg = load_config(etc / "socd.toml")
    assert cfg.dbc.input == DEFAULT_INPUT_DBC
    assert cfg.dbc.output == assets.dbc_path("socd_output.dbc")
    assert cfg.cell_profile == DEFAULT_CELL_PROFILE
    assert cfg.checkpoint.path == tmp_path / "state" / "socd-state.npz"


def test_a_users_file_beside_the_config_wins_over_the_packaged_one(tmp_path):
    (tmp_path / "bms_pack.dbc").write_text((ROOT / "dbc" / "bms_pack.dbc").read_text())
    (tmp_path / "c.toml").write_text('[dbc]\ninput = "bms_pack.dbc"\n')
    assert load_config(tmp_path / "c.toml").dbc.input == tmp_path / "bms_pack.dbc"


def test_a_file_neither_local_nor_packaged_names_the_field(tmp_path):
    (tmp_path / "c.toml").write_text('[dbc]\ninput = "../dbc/acme_pack.dbc"\n')
    with pytest.raises(ConfigError, match=r"c\.toml: dbc\.input: no such file .*acme_pack\.dbc, "
                                          r"and socd ships no file of that name \(it ships bms_pack\.dbc"):
        load_config(tmp_path / "c.toml")
    (tmp_path / "c.toml").write_text('cell_profile = "cells/unknown_cell.toml"\n')
    with pytest.raises(ConfigError, match=r"cell_profile: no such file .*unknown_cell\.toml, and socd "
                                          r"ships no file of that name \(it ships .*panasonic_18650pf\.toml"):
        load_config(tmp_path / "c.toml")


def test_an_absolute_path_is_never_replaced(tmp_path):
    (tmp_path / "c.toml").write_text(f'[dbc]\ninput = "{tmp_path / "gone" / "bms_pack.dbc"}"\n')
    with pytest.raises(ConfigError, match=r"dbc\.input: no such file .*gone/bms_pack\.dbc \(socd's own "
                                          r"bms_pack\.dbc is "):
        load_config(tmp_path / "c.toml")


def test_config_option_falls_back_to_a_packaged_example(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert load_config("vcan0.toml").bus.channel == "vcan0"
    assert load_config("configs/socketcan_can0.toml").bus.channel == "can0"
    (tmp_path / "vcan0.toml").write_text('[bus]\nchannel = "mine"\n')
    assert load_config("vcan0.toml").bus.channel == "mine"  # a file in the working directory wins
    with pytest.raises(ConfigError, match=r"nope\.toml: cannot read config: .*socd ships these examples: "
                                          r"default\.toml, socketcan_can0\.toml"):
        load_config("nope.toml")


def test_checkpoint_default_is_in_the_state_directory_and_writable(tmp_path, monkeypatch):
    from service.daemon.checkpoint import load_checkpoint, save_checkpoint

    monkeypatch.chdir(tmp_path)
    assert default_checkpoint_path() == Path("socd-state.npz")
    state = tmp_path / "var" / "lib" / "socd"
    state.mkdir(parents=True)
    # systemd passes a colon-separated list when a unit has several state directories
    monkeypatch.setenv("STATE_DIRECTORY", f"{state}:{tmp_path / 'other'}")
    cfg = load_config("default.toml")
    assert cfg.checkpoint.path == state / "socd-state.npz"
    save_checkpoint(cfg.checkpoint.path, {"soc": np.array([0.5, 0.6])}, n_cells=2, profile_sha256="x", t_s=1.0)
    loaded = load_checkpoint(cfg.checkpoint.path, n_cells=2, profile_sha256="x")
    assert loaded.ok, loaded.detail


def test_a_packaged_file_the_code_cites_is_package_data():
    """`socd demo` says the bundled drive starts full "(service/data/README.md)", a file the wheel did not
    ship (package data took the recordings only): a user with the wheel could not read the source."""
    from fnmatch import fnmatch

    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["service"]
    cited = {m for f in [*(ROOT / "service").rglob("*.py"), *(ROOT / "replay").rglob("*.py")]
             for m in re.findall(r"service/(data/[\w.]+\.\w+)", f.read_text())}
    assert "data/README.md" in cited
    for name in sorted(cited):
        assert (ROOT / "service" / name).is_file() and any(fnmatch(name, p) for p in patterns), name


def test_missing_extra_names_the_pip_extra():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert set(EXTRA_OF_MODULE.values()) <= set(declared)
    assert install_hint("scipy") == "needs scipy, which is not installed: pip install 'socd[fit]'"
    assert missing_extra(ModuleNotFoundError("x", name="scipy.optimize")) == install_hint("scipy")
    assert missing_extra(ModuleNotFoundError("x", name="numpy")) is None
    assert missing_extra(ImportError("x")) is None


def test_cli_reports_a_missing_extra_in_one_line(monkeypatch, capsys):
    import service.demo
    from service import cli

    # a command that imports an extra's module when it runs
    def run_demo_without_scipy(*_args, **_kwargs):
        raise ModuleNotFoundError("No module named 'scipy'", name="scipy")

    monkeypatch.setattr(service.demo, "run_demo", run_demo_without_scipy)
    assert cli.main(["demo", "--seconds", "5"]) == 3
    assert capsys.readouterr().err == "socd demo: needs scipy, which is not installed: pip install 'socd[fit]'\n"

    # a command whose module cannot be imported at all gets a stand-in saying the same
    real_import = importlib.import_module

    def import_without_matplotlib(name: str, *args):
        if name == cli.SUBCOMMANDS["fit"]:
            raise ModuleNotFoundError("No module named 'matplotlib'", name="matplotlib")
        return real_import(name, *args)

    monkeypatch.setattr(importlib, "import_module", import_without_matplotlib)
    assert cli.main(["fit"]) == 3
    assert capsys.readouterr().err == "socd fit: needs matplotlib, which is not installed: pip install 'socd[fit]'\n"


def test_replay_mf4_without_asammdf_names_the_extra(tmp_path, monkeypatch, capsys):
    import replay.cli
    from service.cli import main

    monkeypatch.setattr(replay.cli, "installed", lambda module: module != "asammdf")
    log = tmp_path / "pack.mf4"
    log.write_bytes(b"")
    assert main(["replay", str(log)]) == 3
    assert capsys.readouterr().err.strip() == (
        f"socd replay: error: {log}: MF4 needs asammdf, which is not installed: pip install 'socd[mf4]'"
    )


def test_demo_without_matplotlib_says_which_extra(monkeypatch, capsys):
    import service.extras
    from service.cli import main

    monkeypatch.setattr(service.extras, "installed", lambda module: module != "matplotlib")
    assert main(["demo", "--plot", "x.png", "--seconds", "5"]) == 3
    assert capsys.readouterr().err.strip() == (
        "socd demo: error: --plot needs matplotlib, which is not installed: pip install 'socd[fit]'"
    )


def test_a_flag_whose_extra_is_missing_exits_3_at_once(tmp_path, monkeypatch, capsys):
    """The README promises exit 3 for a missing optional extra: `socd demo --plot` and an MF4 log in
    `socd replay` exited 2 (above), and `socd watch --plot` waited for the service and failed only when
    its first data came, or timed out with exit 1 where none came, without naming the extra."""
    import service.extras
    from service.cli import main

    monkeypatch.setattr(service.extras, "installed", lambda module: module != "matplotlib")
    started = time.monotonic()
    assert main(["watch", "--once", "--timeout", "3", "--plot", str(tmp_path / "w.png")]) == 3
    assert time.monotonic() - started < 2
    assert capsys.readouterr().err.strip() == (
        "socd watch: error: --plot needs matplotlib, which is not installed: pip install 'socd[fit]'"
    )


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_unit_verifies(tmp_path):
    unit = (ROOT / "deploy" / "socd.service").read_text()
    assert re.search(r"^DynamicUser=yes$", unit, re.MULTILINE) and re.search(r"^StateDirectory=socd$", unit, re.MULTILINE)
    assert not re.search(r"^(User|Group)=", unit, re.MULTILINE)
    exec_start = re.search(r"^ExecStart=(\S+) run --config /etc/socd/socd.toml$", unit, re.MULTILINE)
    assert exec_start
    # verify checks that ExecStart's program exists: point it at this environment's socd
    socd = Path(sys.executable).parent / "socd"
    if not socd.exists():
        pytest.skip(f"no socd entry point beside {sys.executable}")
    (tmp_path / "socd.service").write_text(unit.replace(exec_start.group(1), str(socd)))
    done = subprocess.run(["systemd-analyze", "verify", str(tmp_path / "socd.service")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stderr == "", done.stderr


def test_dockerfile_runs_socd_as_a_non_root_user_with_a_state_volume():
    text = (ROOT / "Dockerfile").read_text()
    instructions = [line for line in text.splitlines() if line and not line.startswith(("#", " "))]
    last_stage = instructions[max(i for i, line in enumerate(instructions) if line.startswith("FROM")):]
    assert 'ENTRYPOINT ["socd"]' in last_stage
    assert 'CMD ["run", "--config", "socketcan_can0.toml"]' in last_stage
    assert "USER 10001:10001" in last_stage
    assert 'VOLUME ["/var/lib/socd"]' in last_stage
    assert any(line.startswith("HEALTHCHECK") for line in last_stage)
    assert re.search(r"STATE_DIRECTORY=/var/lib/socd", text)
    assert re.search(r"install -d -o socd -g socd -m 0750 /var/lib/socd", text)
    # the default command's config is one the package ships
    assert assets.config_path("socketcan_can0.toml").is_file()


def test_docker_health_check_is_the_checkpoint_age(tmp_path):
    text = (ROOT / "Dockerfile").read_text()
    health = re.search(r"^HEALTHCHECK .*\\\n\s+CMD (\[.*\])$", text, re.MULTILINE)
    assert health, "HEALTHCHECK ... CMD [exec form] not found"
    argv = json.loads(health.group(1))
    checkpoint = tmp_path / "socd-state.npz"

    def healthy() -> bool:
        env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "STATE_DIRECTORY": str(tmp_path)}
        return subprocess.run(argv, env=env, capture_output=True, timeout=30).returncode == 0

    assert not healthy()  # no checkpoint yet: the daemon has not estimated anything
    checkpoint.write_bytes(b"x")
    assert healthy()
    old = time.time() - 180
    os.utime(checkpoint, (old, old))
    assert not healthy()  # not rewritten for three minutes


def test_a_command_that_fails_half_way_through_its_parser_leaves_the_others_working(monkeypatch, capsys):
    """A module whose ``add_subparser`` raises after adding its parser (a broken install) gets the
    stand-in on that parser; every other command still parses."""
    import types

    from service import cli

    def half_built(subparsers):
        subparsers.add_parser("schema")
        raise NameError("name 'float_in' is not defined")

    real_import = importlib.import_module

    def import_half_built(name: str, *args):
        if name == cli.SUBCOMMANDS["schema"]:
            return types.SimpleNamespace(add_subparser=half_built)
        return real_import(name, *args)

    monkeypatch.setattr(importlib, "import_module", import_half_built)
    assert cli.main(["schema"]) == 3
    assert "float_in" in capsys.readouterr().err
    assert cli.main(["check", "--help"]) == 0
