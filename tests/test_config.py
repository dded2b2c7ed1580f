"""SocdConfig: TOML + SOCD_* environment, validation errors that name the field."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest

from service.cell.profile import CellProfile, save_profile
from service.config import ConfigError, SocdConfig, build_config, load_config

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
OCV_TABLE = Path("/work/shared/data/real/ocv/ocv_pan18650pf_25C_soc_table.csv")
BUNDLED_PROFILE = CONFIGS / "cells" / "panasonic_18650pf.toml"


def write_test_profile(path: Path) -> Path:
    """A small valid cell profile (OCV from the shared table when present, else synthetic)."""
    if OCV_TABLE.is_file():
        rows = list(csv.DictReader(OCV_TABLE.open()))
        soc = [float(r["soc"]) for r in rows]
        ocv = [float(r["ocv_avg_v"]) for r in rows]
    else:
        soc = [i / 20 for i in range(21)]
        ocv = [3.0 + 1.2 * s for s in soc]
    profile = CellProfile(
        name="test", capacity_ah=2.77, ocv={"soc": soc, "ocv_v": [ocv]},
        parameters=[{"r_ohm": 0.02, "r_ct": 0.01, "c_dl": 500.0, "m": 0.8, "r_df": 0.02, "c_df": 5000.0, "n": 0.6}],
    )
    save_profile(profile, path)
    return path


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    for k in list(os.environ):
        if k.upper().startswith("SOCD_"):
            monkeypatch.delenv(k)


@pytest.fixture
def profile(tmp_path, monkeypatch):
    """Point cell_profile at the bundled profile if the lead shipped it, else a test one."""
    if BUNDLED_PROFILE.is_file():
        return BUNDLED_PROFILE
    p = write_test_profile(tmp_path / "cell.toml")
    monkeypatch.setenv("SOCD_CELL_PROFILE", str(p))
    return p


def write(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_default_config_loads(profile):
    cfg = load_config(CONFIGS / "default.toml")
    assert cfg.pack.n_cells == 96
    assert cfg.bus.interface == "virtual"
    assert cfg.mapping.cell_voltage_signals[0] == "BMS_Cell001_V"
    assert cfg.mapping.cell_voltage_signals[95] == "BMS_Cell096_V"
    assert len(cfg.mapping.temperature_signals) == 24
    assert cfg.mapping.temperature_signals[1].cells == [4, 5, 6, 7]
    assert cfg.mapping.current_sign == -1.0
    assert cfg.dbc.input == ROOT / "dbc" / "bms_pack.dbc"
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:7447"] and cfg.zenoh.scouting_multicast is False
    assert cfg.cell_profile == profile.resolve()
    assert cfg.zenoh_key("cell", 3, "soc") == "bms/pack0/cell/3/soc"
    assert cfg.estimator.memory_length >= 1
    assert cfg.bus.bus_kwargs() == {"interface": "virtual", "channel": "vcan0", "receive_own_messages": False,
                                    "preserve_timestamps": True}


def test_load_config_without_path_is_default(profile):
    assert load_config().pack.n_cells == 96


@pytest.mark.parametrize("name", ["vcan0.toml", "socketcan_can0.toml", "user_dbc_example/acme.toml"])
def test_shipped_configs_validate(name, profile):
    cfg = load_config(CONFIGS / name)
    assert cfg.zenoh.scouting_multicast is False
    assert all("127.0.0.1" in e for e in cfg.zenoh.listen)


def test_user_dbc_config_maps_other_names(profile):
    cfg = load_config(CONFIGS / "user_dbc_example" / "acme.toml")
    assert cfg.pack.n_cells == 12
    assert cfg.mapping.current_signal == "ACME_Idc" and cfg.mapping.current_sign == 1.0
    assert cfg.dbc.input.name == "acme_bms.dbc"
    assert cfg.mapping.sensor_of_cell(12) == [0] * 5 + [1] * 5 + [2] * 2


def test_env_overrides_file(profile, monkeypatch, tmp_path):
    monkeypatch.setenv("SOCD_BUS__CHANNEL", "can7")
    monkeypatch.setenv("SOCD_BUS__INTERFACE", "socketcan")
    monkeypatch.setenv("SOCD_ESTIMATOR__MEMORY_LENGTH", "32")
    monkeypatch.setenv("SOCD_ZENOH__PACK_ID", "packB")
    cfg = load_config(CONFIGS / "default.toml")
    assert cfg.bus.channel == "can7" and cfg.bus.interface == "socketcan"
    assert cfg.bus.bitrate == 500000  # the rest of [bus] still comes from the file
    assert cfg.estimator.memory_length == 32
    assert cfg.zenoh_key("summary") == "bms/packB/summary"


def test_env_typo_is_an_error(profile, monkeypatch):
    monkeypatch.setenv("SOCD_BUS__CHANEL", "can0")
    with pytest.raises(ConfigError, match=r"bus\.chanel"):
        load_config(CONFIGS / "default.toml")


def test_relative_paths_resolve_against_config_dir(tmp_path, profile):
    sub = tmp_path / "site"
    sub.mkdir()
    (sub / "my.dbc").write_text((ROOT / "dbc" / "bms_pack.dbc").read_text())
    cfg = load_config(write(sub, f'cell_profile = "{profile}"\n[dbc]\ninput = "my.dbc"\n'
                                 '[checkpoint]\npath = "state/x.npz"\n'))
    assert cfg.dbc.input == sub / "my.dbc"
    assert cfg.checkpoint.path == sub / "state" / "x.npz"


def test_unknown_key_names_field(tmp_path, profile):
    with pytest.raises(ConfigError) as e:
        load_config(write(tmp_path, '[bus]\nchanel = "can0"\n'))
    assert "c.toml: bus.chanel: unknown key (did you mean channel?)" in str(e.value)
    with pytest.raises(ConfigError, match=r"c\.toml: buss: unknown key \(did you mean bus\?\)"):
        load_config(write(tmp_path, '[buss]\nchannel = "can0"\n'))


def test_bad_type_names_field(tmp_path, profile):
    with pytest.raises(ConfigError, match=r"bus\.bitrate: "):
        load_config(write(tmp_path, '[bus]\nbitrate = "fast"\n'))
    with pytest.raises(ConfigError, match=r"estimator\.memory_length: "):
        load_config(write(tmp_path, "[estimator]\nmemory_length = 0\n"))
    with pytest.raises(ConfigError, match=r"zenoh\.mode: "):
        load_config(write(tmp_path, '[zenoh]\nmode = "server"\n'))
    with pytest.raises(ConfigError, match=r"mapping\.voltage_range_v: .*low < high"):
        load_config(write(tmp_path, "[mapping]\nvoltage_range_v = [4.8, 1.5]\n"))


def test_unknown_signal_names_field_and_signal(tmp_path, profile):
    sigs = [f"BMS_Cell{i:03d}_V" for i in range(1, 13)]
    sigs[3] = "BMS_Cell04_V"
    text = ("[pack]\nn_cells = 12\n[mapping]\ncell_voltage_signals = [" + ", ".join(f'"{s}"' for s in sigs)
            + ']\ntemperature_pattern = "BMS_Temp{number:02d}_C"\n')
    with pytest.raises(ConfigError) as e:
        load_config(write(tmp_path, text))
    msg = str(e.value)
    assert "mapping.cell_voltage_signals[3]" in msg and "'BMS_Cell04_V'" in msg and "did you mean" in msg
    with pytest.raises(ConfigError, match=r"mapping\.current_signal: signal 'BMS_PackCurent'"):
        load_config(write(tmp_path, '[mapping]\ncurrent_signal = "BMS_PackCurent"\n'))
    with pytest.raises(ConfigError, match=r"mapping\.counter_signals\.BMS_Nope: message"):
        load_config(write(tmp_path, '[mapping.counter_signals]\nBMS_Nope = "X"\n'))


def test_cell_count_mismatch(tmp_path, profile):
    text = '[pack]\nn_cells = 4\n[mapping]\ncell_voltage_signals = ["BMS_Cell001_V", "BMS_Cell002_V", "BMS_Cell003_V"]\n'
    with pytest.raises(ConfigError, match=r"mapping\.cell_voltage_signals: has 3 signals but pack\.n_cells is 4"):
        load_config(write(tmp_path, text))


def test_n_cells_inferred_from_explicit_list(tmp_path, profile):
    text = ('[mapping]\ncell_voltage_signals = ["BMS_Cell001_V", "BMS_Cell002_V", "BMS_Cell003_V"]\n'
            'temperature_signals = [{signal = "BMS_Temp01_C", cells = [0, 1, 2]}]\n')
    cfg = load_config(write(tmp_path, text))
    assert cfg.pack.n_cells == 3


def test_temperature_map_errors(tmp_path, profile):
    base = '[pack]\nn_cells = 8\n[mapping]\n'
    with pytest.raises(ConfigError, match=r"mapping\.temperature_signals\[1\]\.cells\[0\]: cell 9 outside 0\.\.7"):
        load_config(write(tmp_path, base + 'temperature_signals = [{signal = "BMS_Temp01_C", cells = [0,1,2,3]},'
                                           ' {signal = "BMS_Temp02_C", cells = [9]}]\n'))
    with pytest.raises(ConfigError, match=r"cell\(s\) \[4, 5, 6, 7\] covered by no temperature sensor"):
        load_config(write(tmp_path, base + 'temperature_signals = [{signal = "BMS_Temp01_C", cells = [0,1,2,3]}]\n'))
    with pytest.raises(ConfigError, match=r"mapping\.temperature_signals\[0\]\.cells: "):
        load_config(write(tmp_path, base + 'temperature_signals = [{signal = "BMS_Temp01_C", cells = []}]\n'))


def test_duplicate_signal_is_an_error(tmp_path, profile):
    text = ('[mapping]\ncell_voltage_signals = ["BMS_Cell001_V", "BMS_Cell001_V"]\n'
            'temperature_signals = [{signal = "BMS_Temp01_C", cells = [0, 1]}]\n')
    with pytest.raises(ConfigError, match=r"mapping\.cell_voltage_signals\[1\]: signal 'BMS_Cell001_V' is already"):
        load_config(write(tmp_path, text))


def test_cells_form_and_conflicting_forms(tmp_path, profile):
    text = ('[mapping]\ncells = [{cell = 1, signal = "BMS_Cell002_V"}, {cell = 0, signal = "BMS_Cell001_V"}]\n'
            'temperature_signals = [{signal = "BMS_Temp01_C", cells = [0, 1]}]\n')
    cfg = load_config(write(tmp_path, text))
    assert cfg.mapping.cell_voltage_signals == ["BMS_Cell001_V", "BMS_Cell002_V"]
    text = ('[pack]\nn_cells = 2\n[mapping]\ncell_voltage_signals = ["BMS_Cell002_V", "BMS_Cell001_V"]\n'
            'cell_voltage_pattern = "BMS_Cell{number:03d}_V"\n')
    with pytest.raises(ConfigError, match=r"mapping\.cell_voltage_pattern: conflicts"):
        load_config(write(tmp_path, text))
    with pytest.raises(ConfigError, match=r"mapping\.cell_voltage_pattern: "):
        load_config(write(tmp_path, '[mapping]\ncell_voltage_pattern = "BMS_Cell{cell}_V"\n'))


def test_bad_toml_and_missing_file(tmp_path, profile):
    with pytest.raises(ConfigError, match=r"c\.toml: not valid TOML"):
        load_config(write(tmp_path, "[bus\n"))
    with pytest.raises(ConfigError, match=r"nope\.toml: cannot read config"):
        load_config(tmp_path / "nope.toml")


def test_missing_profile_and_dbc_name_the_field(tmp_path, profile, monkeypatch):
    monkeypatch.delenv("SOCD_CELL_PROFILE", raising=False)
    with pytest.raises(ConfigError, match=r"c\.toml: cell_profile: no such file .*nothere\.toml"):
        load_config(write(tmp_path, 'cell_profile = "nothere.toml"\n'))
    with pytest.raises(ConfigError, match=r"dbc\.input: no such file"):
        load_config(write(tmp_path, f'cell_profile = "{profile}"\n[dbc]\ninput = "missing.dbc"\n'))
    (tmp_path / "bad.dbc").write_text("this is not a dbc")
    with pytest.raises(ConfigError, match=r"dbc\.output: cannot load DBC"):
        load_config(write(tmp_path, f'cell_profile = "{profile}"\n[dbc]\noutput = "bad.dbc"\n'))


def test_dump_and_revalidate_roundtrip(profile):
    cfg = load_config(CONFIGS / "default.toml")
    again = build_config(cfg.model_dump(mode="json"))
    assert again.mapping.cell_voltage_signals == cfg.mapping.cell_voltage_signals
    assert again.mapping.temperature_signals == cfg.mapping.temperature_signals


def test_bus_kwargs():
    cfg = SocdConfig()
    assert cfg.bus.bus_kwargs() == {"interface": "virtual", "channel": "vcan0", "receive_own_messages": False}
    cfg = build_config({"bus": {"interface": "socketcan", "channel": "can0", "fd": True, "data_bitrate": 2000000}})
    assert cfg.bus.bus_kwargs()["bitrate"] == 500000 and cfg.bus.bus_kwargs()["data_bitrate"] == 2000000


@pytest.mark.parametrize("given", ["vcan0.toml", "configs/vcan0.toml", "user_dbc_example/acme.toml"])
def test_a_name_of_socds_layout_finds_the_packaged_example(tmp_path, monkeypatch, given):
    """From any folder, the README's ``--config configs/vcan0.toml`` and an example's own name load
    the packaged example."""
    monkeypatch.chdir(tmp_path)
    assert load_config(given).bus.interface in ("socketcan", "virtual")


def test_a_missing_config_of_ones_own_is_not_replaced_by_the_example(tmp_path, monkeypatch):
    """``--config nosuch/vcan0.toml`` loaded the packaged vcan0.toml and `socd check` said OK."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"nosuch/vcan0\.toml: cannot read config"):
        load_config("nosuch/vcan0.toml")


def test_a_missing_dbc_of_ones_own_is_named_not_replaced_by_the_example(tmp_path, profile):
    """``[dbc] input = "mine/bms_pack.dbc"`` not deployed: the packaged DBC of that name was decoded
    without a word.  The examples' own ``../dbc/bms_pack.dbc`` still finds the packaged one."""
    with pytest.raises(ConfigError, match=r"dbc\.input: no such file .*mine/bms_pack\.dbc"):
        load_config(write(tmp_path, f'cell_profile = "{profile}"\n[dbc]\ninput = "mine/bms_pack.dbc"\n'))
    cfg = load_config(write(tmp_path, f'cell_profile = "{profile}"\n[dbc]\ninput = "../dbc/bms_pack.dbc"\n'))
    assert cfg.dbc.input.name == "bms_pack.dbc" and cfg.dbc.input.is_file()
