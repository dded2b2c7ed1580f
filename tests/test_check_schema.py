"""``socd check`` on good and broken configs; ``socd schema`` output validates its own examples."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.cli import main

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "configs" / "default.toml"
DBC = ROOT / "dbc" / "bms_pack.dbc"


def _config(tmp_path: Path, *, dbc: Path | None = None, replace: dict[str, str] | None = None,
            extra: str = "") -> Path:
    text = DEFAULT.read_text()
    text = text.replace('cell_profile = "cells/', f'cell_profile = "{ROOT}/configs/cells/')
    text = text.replace('"../dbc/bms_pack.dbc"', f'"{dbc or DBC}"').replace('"../dbc/', f'"{ROOT}/dbc/')
    for old, new in (replace or {}).items():
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / "socd.toml"
    path.write_text(text + extra)
    return path


@pytest.mark.parametrize("config", ["default.toml", "vcan0.toml", "socketcan_can0.toml", "user_dbc_example/acme.toml"])
def test_shipped_configs_pass(config: str, capsys) -> None:
    assert main(["check", "--config", str(ROOT / "configs" / config)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].endswith(": OK")
    for label in ("pack", "input DBC", "output DBC", "cell profile", "bus", "zenoh", "metrics", "checkpoint"):
        assert any(line.strip().startswith(label) for line in out.splitlines()), label
    assert len(out.splitlines()) <= 24  # one screen


def test_every_mapping_problem_is_one_line(tmp_path: Path, capsys) -> None:
    path = _config(tmp_path, replace={
        'current_signal = "BMS_PackCurrent"': 'current_signal = "BMS_PackCurent"',
        'BMS_CellTemps = "BMS_CellTempCounter"': 'BMS_CellTemps = "BMS_NoCounter"',
    })
    assert main(["check", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2, err
    assert err[0] == (f"{path}: mapping.current_signal: signal 'BMS_PackCurent' not in dbc.input (bms_pack.dbc); "
                      "did you mean 'BMS_PackCurrent'?")
    assert err[1] == (f"{path}: mapping.counter_signals.BMS_CellTemps: signal 'BMS_NoCounter' not in message "
                      "'BMS_CellTemps' of dbc.input")


def test_multiplexer_problems(tmp_path: Path, capsys) -> None:
    text = DBC.read_text()
    switch = 'SG_ BMS_CellVoltMux M : 0|8@1+ (1,0) [0|23]'
    assert switch in text
    narrow = tmp_path / "narrow_mux.dbc"
    narrow.write_text(text.replace(switch, 'SG_ BMS_CellVoltMux M : 0|8@1+ (1,0) [0|21]'))
    path = _config(tmp_path, dbc=narrow)
    assert main(["check", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # cells 88..95 ride on mux values 22 and 23, outside the switch's declared range
    assert len(err) == 8, err
    assert all("is multiplexed on BMS_CellVoltMux value(s) [2" in line and "outside the switch's range 0..21" in line
               for line in err)
    assert err[0].startswith(f"{path}: mapping.cell_voltage_signals[88]: signal 'BMS_Cell089_V'")

    path = _config(tmp_path, replace={'current_signal = "BMS_PackCurrent"': 'current_signal = "BMS_CellVoltMux"'})
    assert main(["check", "--config", str(path)]) == 2
    assert "mapping.current_signal: signal 'BMS_CellVoltMux' is the multiplexer switch of BMS_CellVoltages" in \
        capsys.readouterr().err


def test_field_errors_files_and_cell_indices(tmp_path: Path, capsys) -> None:
    path = _config(tmp_path, replace={"n_cells = 96": "n_cells = 0"})
    assert main(["check", "--config", str(path)]) == 2
    assert f"{path}: pack.n_cells: Input should be greater than or equal to 1" in capsys.readouterr().err

    extra = '\n[[mapping.temperature_signals]]\nsignal = "BMS_Temp01_C"\ncells = [0, 96]\n'
    path = _config(tmp_path, replace={'temperature_pattern = "BMS_Temp{number:02d}_C"': "",
                                      "cells_per_sensor = 4": ""})
    path.write_text(path.read_text().replace("[mapping.counter_signals]", extra + "\n[mapping.counter_signals]"))
    assert main(["check", "--config", str(path)]) == 2
    assert "mapping.temperature_signals[0].cells[1]: cell 96 outside 0..95" in capsys.readouterr().err

    path = _config(tmp_path, dbc=tmp_path / "missing.dbc",
                   replace={'interface = "virtual"': 'interface = "no_such_bus"',
                            'pack_id = "pack0"': f'pack_id = "pack0"\nconfig_file = "{tmp_path / "nope.json5"}"'})
    assert main(["check", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == f"{path}: dbc.input: no such file {tmp_path / 'missing.dbc'}"
    assert any(line.startswith(f"{path}: bus.interface: unknown python-can interface 'no_such_bus'") for line in err)
    assert any(line.startswith(f"{path}: zenoh.config_file: {tmp_path / 'nope.json5'}: No such file") for line in err)


def test_schema_files_validate_their_examples(tmp_path: Path, capsys) -> None:
    from service.daemon import payloads

    out = tmp_path / "schema"
    assert main(["schema", "-o", str(out)]) == 0
    models = {"cell_soc": payloads.CellSoc, "cell_params": payloads.CellParams, "summary": payloads.Summary,
              "health": payloads.Health, "snapshot": payloads.Snapshot}
    for name, model in models.items():
        schema = json.loads((out / f"{name}.schema.json").read_text())
        example = json.loads((out / f"{name}.example.json").read_text())
        assert schema == model.model_json_schema()
        assert set(example) <= set(schema["properties"]) and set(schema.get("required", [])) <= set(example)
        assert model.model_validate(example).model_dump(mode="json") == example
        assert example["schema_version"] == model.model_fields["schema_version"].default
    # a payload's version moves with its own shape: the summary (and the snapshot holding one) gained the pack view, the cell params the capacity
    versions = {name: json.loads((out / f"{name}.example.json").read_text())["schema_version"] for name in models}
    assert versions == {"cell_soc": 1, "cell_params": 2, "summary": 2, "health": 1, "snapshot": 2}
    snap = payloads.Snapshot.model_validate_json((out / "snapshot.example.json").read_text())
    assert len(snap.cells) == snap.summary.n_cells == 2 and snap.summary.cell_min == 1
    summary = json.loads((out / "summary.example.json").read_text())
    for field in ("usable_soc_pct", "usable_discharge_ah", "usable_charge_ah", "remaining_energy_wh",
                  "usable_energy_wh", "imbalance_ah", "weakest_cell", "fullest_cell"):
        assert summary[field] is not None and field in payloads.Summary.model_json_schema()["properties"]
    # without -o: one JSON document on stdout with the same content
    capsys.readouterr()
    assert main(["schema"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == set(models) | {"config"} and doc["summary"]["key"] == "bms/pack0/summary"
    assert doc["cell_soc"]["example"] == json.loads((out / "cell_soc.example.json").read_text())
    # -o onto a file is refused
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["schema", "-o", str(f)]) == 2


def test_schema_writes_the_configs_schema_and_the_default_config_as_its_example(tmp_path: Path) -> None:
    """The README says `socd schema` prints the config's JSON schema; it printed the payloads' alone."""
    from service.config import SocdConfig, load_config

    out = tmp_path / "schema"
    assert main(["schema", "-o", str(out)]) == 0
    schema = json.loads((out / "config.schema.json").read_text())
    assert schema == SocdConfig.model_json_schema()
    assert {"bus", "dbc", "mapping", "estimator", "zenoh", "checkpoint", "pack"} <= set(schema["properties"])
    example = json.loads((out / "config.example.json").read_text())
    assert example == load_config(None, check_files=False).model_dump(mode="json")
    assert SocdConfig.model_validate(example).pack.n_cells == example["pack"]["n_cells"]


def test_docs_examples_are_what_socd_schema_writes(tmp_path: Path) -> None:
    """The example payloads quoted in docs/zenoh.md equal the command's own output."""
    import re

    out = tmp_path / "schema"
    assert main(["schema", "-o", str(out)]) == 0
    doc = (ROOT / "docs" / "zenoh.md").read_text()
    blocks = [json.loads(b) for b in re.findall(r"```json\n(.*?)```", doc, re.DOTALL)]
    assert blocks[0] == json.loads((out / "cell_soc.example.json").read_text())
    assert blocks[1] == json.loads((out / "summary.example.json").read_text())
