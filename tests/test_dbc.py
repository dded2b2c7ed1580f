"""The shipped DBCs: load strictly with cantools, look like a real BMS bus, match the generator."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cantools
import pytest

from service.bus.types import STATUS_FLAGS

ROOT = Path(__file__).resolve().parent.parent
DBC = ROOT / "dbc"


@pytest.fixture(scope="module")
def gen():
    spec = importlib.util.spec_from_file_location("generate_dbc", DBC / "generate_dbc.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def bms():
    return cantools.database.load_file(DBC / "bms_pack.dbc", strict=True)


@pytest.fixture(scope="module")
def out():
    return cantools.database.load_file(DBC / "socd_output.dbc", strict=True)


def test_committed_files_match_generator(gen, tmp_path):
    gen.main(["--out-dir", str(tmp_path), "--user-example", str(tmp_path / "acme_bms.dbc")])
    for name in ("bms_pack.dbc", "socd_output.dbc"):
        assert (tmp_path / name).read_text() == (DBC / name).read_text(), f"{name} is stale: rerun the generator"
    acme = ROOT / "configs" / "user_dbc_example" / "acme_bms.dbc"
    assert (tmp_path / "acme_bms.dbc").read_text() == acme.read_text()


def test_generator_other_sizes(gen, tmp_path):
    gen.main(["--cells", "13", "--temps", "5", "--out-dir", str(tmp_path)])
    db = cantools.database.load_file(tmp_path / "bms_pack.dbc", strict=True)
    names = {s.name for m in db.messages for s in m.signals}
    assert "BMS_Cell013_V" in names and "BMS_Cell014_V" not in names
    assert "BMS_Temp05_C" in names


def test_input_bus_layout(bms):
    pack = bms.get_message_by_name("BMS_PackStatus")
    assert pack.frame_id == 0x100 and pack.cycle_time == 10 and not pack.is_extended_frame
    cur = pack.get_signal_by_name("BMS_PackCurrent")
    assert cur.is_signed and cur.scale == 0.05 and cur.length == 16
    assert pack.get_signal_by_name("BMS_PackCounter").length == 4
    volts = bms.get_message_by_name("BMS_CellVoltages")
    cells = [s for s in volts.signals if s.name.startswith("BMS_Cell") and s.name.endswith("_V")]
    assert len(cells) == 96
    assert all(s.scale <= 0.001 and 13 <= s.length <= 16 for s in cells)
    mux = volts.get_signal_by_name("BMS_CellVoltMux")
    assert mux.is_multiplexer
    per_mux = {}
    for s in cells:
        (m,) = s.multiplexer_ids
        per_mux.setdefault(m, []).append(s.name)
    assert len(per_mux) == 24 and all(len(v) == 4 for v in per_mux.values())
    assert per_mux[2] == ["BMS_Cell009_V", "BMS_Cell010_V", "BMS_Cell011_V", "BMS_Cell012_V"] or \
        sorted(per_mux[2]) == ["BMS_Cell009_V", "BMS_Cell010_V", "BMS_Cell011_V", "BMS_Cell012_V"]
    temps = bms.get_message_by_name("BMS_CellTemps")
    tsig = [s for s in temps.signals if s.name.startswith("BMS_Temp")]
    assert len(tsig) == 24 and all(s.is_signed for s in tsig)
    assert all(m.length <= 8 for m in bms.messages)


def test_cell_voltage_roundtrip_resolution(bms):
    m = bms.get_message_by_name("BMS_CellVoltages")
    data = {"BMS_CellVoltMux": 23, "BMS_CellVoltCounter": 15, "BMS_Cell093_V": 2.5004,
            "BMS_Cell094_V": 3.6999, "BMS_Cell095_V": 4.2, "BMS_Cell096_V": 0.0}
    back = m.decode(m.encode(data))
    for k, v in data.items():
        assert back[k] == pytest.approx(v, abs=0.0005)


def test_output_frames(out):
    for m in out.messages:
        assert m.is_extended_frame and m.frame_id > 0x7FF and m.length <= 8
        assert m.senders == ["SOCD"]
    soc = out.get_message_by_name("SOCD_CellSoc")
    assert soc.get_signal_by_name("SOCD_Soc").scale == 0.01
    # one signal set valid for every cell index (multiplexed per cell)
    assert len(soc.get_signal_by_name("SOCD_Soc").multiplexer_ids) == 256
    frame = soc.encode({"SOCD_SocCellIndex": 200, "SOCD_Soc": 55.55, "SOCD_SocStd": 1.25,
                        "SOCD_SocStale": 0, "SOCD_SocCounter": 3})
    back = soc.decode(frame)
    assert back["SOCD_SocCellIndex"] == 200 and back["SOCD_Soc"] == pytest.approx(55.55)
    params = out.get_message_by_name("SOCD_CellParams")
    assert {s.name for s in params.signals} >= {"SOCD_ROhm", "SOCD_RCt", "SOCD_RDf", "SOCD_M", "SOCD_N"}


def test_status_word_bits_match_types(out, gen):
    status = out.get_message_by_name("SOCD_Status")
    flags = sorted((s for s in status.signals if s.name.startswith("SOCD_Flag")), key=lambda s: s.start)
    assert [s.start for s in flags] == list(range(len(STATUS_FLAGS)))
    assert [s.name for s in flags] == ["SOCD_Flag" + gen.camel(f) for f in STATUS_FLAGS]
    for required in ("SOCD_FlagStaleCells", "SOCD_FlagCheckpointRestored", "SOCD_FlagOcvInit",
                     "SOCD_FlagFilterReset", "SOCD_FlagBusError", "SOCD_FlagZenohDown", "SOCD_FlagPublishDrops"):
        assert required in {s.name for s in flags}
    assert max(s.start + s.length for s in flags) <= 32
