"""Bad files given to the tools: exit 2, one line naming the file, no traceback, nothing written.

Every case runs the real command in-process (``service.cli.main``) on a real file; python-can
and cantools parse what they are given.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.cli import main
from service.config import DEFAULT_CELL_PROFILE, DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC

GOOD_ROWS = "\n".join(f"{t},{1.0 if t % 20 < 10 else 0.0},{3.7 - 0.001 * t},25.0" for t in range(60))
HEADER = "time_s,current_a,voltage_v,temperature_c"


def run_cli(capsys, argv: list[str]) -> tuple[int, str]:
    code = main(argv)
    err = capsys.readouterr().err
    return code, err


def assert_one_line_error(code: int, err: str, names: str) -> None:
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and names in lines[0], err


def _recording(tmp: Path, name: str, body: str, header: str = HEADER) -> Path:
    p = tmp / name
    p.write_text(header + "\n" + body + "\n")
    return p


def _with(tmp: Path, name: str, row: int, column: int, value: str) -> Path:
    rows = [r.split(",") for r in GOOD_ROWS.split("\n")]
    rows[row][column] = value
    return _recording(tmp, name, "\n".join(",".join(r) for r in rows))


BAD_RECORDINGS = {
    "other_columns.csv": lambda t: _recording(t, "other_columns.csv", "1,2,3\n4,5,6", header="a,b,c"),
    "semicolons.csv": lambda t: _recording(t, "semicolons.csv", GOOD_ROWS.replace(",", ";"), HEADER.replace(",", ";")),
    "binary.csv": lambda t: (t / "binary.csv").write_bytes(bytes(range(256)) * 8) and t / "binary.csv",
    "latin1.csv": lambda t: (t / "latin1.csv").write_bytes(b"time_s,current_a\n\xe9\xff,1\n") and t / "latin1.csv",
    "header_only.csv": lambda t: _recording(t, "header_only.csv", ""),
    "huge_temp.csv": lambda t: _with(t, "huge_temp.csv", 5, 3, "-1e308"),
    "huge_current.csv": lambda t: _with(t, "huge_current.csv", 7, 1, "1e308"),
    "huge_time.csv": lambda t: _with(t, "huge_time.csv", 59, 0, "1e308"),
    "nan_voltage.csv": lambda t: _with(t, "nan_voltage.csv", 3, 2, "nan"),
    "mv_voltage.csv": lambda t: _with(t, "mv_voltage.csv", 3, 2, "3700"),
    "zero_voltage.csv": lambda t: _with(t, "zero_voltage.csv", 3, 2, "0"),  # a dropped sensor, an empty column
    "time_back.csv": lambda t: _with(t, "time_back.csv", 10, 0, "2"),
    # the logger stopped for two hours with 1 A flowing: the held current would count 2 Ah no sample saw
    "loaded_gap.csv": lambda t: _recording(t, "loaded_gap.csv", "\n".join(
        f"{t_s},1.0,{3.7 - 0.001 * k},25.0" for k, t_s in enumerate([*range(30), *range(7230, 7260)]))),
}

BAD_LOGS = {
    "garbage.blf": b"LOGG" + os.urandom(300),
    "garbage.trc": b";$FILEVERSION=9.9\nnot a trace\n\x01\x02",
    "garbage.log": b"(abc) can0 zzz#xx\nhello\n",
    "garbage.mf4": b"MDF     4.10    " + os.urandom(200),
    "empty.asc": b"",
    "garbage.asc": b"this is not\nan asc file\n",
    "binary.asc": bytes(range(256)),
}


def _replay_argv(path: Path, tmp: Path, *extra: str) -> list[str]:
    return ["replay", str(path), "--no-send", "--record", str(tmp / "out.asc"), "--quiet", *extra]


@pytest.mark.parametrize("name", list(BAD_RECORDINGS))
def test_replay_refuses_bad_recordings(tmp_path: Path, capsys, name: str) -> None:
    path = BAD_RECORDINGS[name](tmp_path)
    code, err = run_cli(capsys, _replay_argv(path, tmp_path))
    assert_one_line_error(code, err, str(path))
    assert not (tmp_path / "out.asc").exists()


@pytest.mark.parametrize("name", list(BAD_LOGS))
def test_replay_refuses_bad_logs(tmp_path: Path, capsys, name: str) -> None:
    path = tmp_path / name
    path.write_bytes(BAD_LOGS[name])
    code, err = run_cli(capsys, _replay_argv(path, tmp_path))
    assert_one_line_error(code, err, str(path))
    assert not (tmp_path / "out.asc").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their mode")
def test_replay_refuses_unreadable_file(tmp_path: Path, capsys) -> None:
    path = _recording(tmp_path, "locked.csv", GOOD_ROWS)
    path.chmod(0)
    code, err = run_cli(capsys, _replay_argv(path, tmp_path))
    assert_one_line_error(code, err, str(path))


def test_bom_recording_is_read(tmp_path: Path, capsys) -> None:
    from service.recording import load_recording

    path = tmp_path / "bom.csv"
    path.write_bytes(b"\xef\xbb\xbf" + (HEADER + "\n" + GOOD_ROWS + "\n").encode())
    assert len(load_recording(path)) == 60


def test_replay_of_a_good_recording_still_works(tmp_path: Path, capsys) -> None:
    path = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, _replay_argv(path, tmp_path, "--cells", "8"))
    assert code == 0, err
    assert (tmp_path / "out.asc").stat().st_size > 0


def _config_file(tmp: Path, dbc: Path, extra: str = "") -> Path:
    cfg = tmp / "socd.toml"
    cfg.write_text(f'cell_profile = "{DEFAULT_CELL_PROFILE}"\n[dbc]\ninput = "{dbc}"\noutput = "{DEFAULT_OUTPUT_DBC}"\n'
                   f"[pack]\nn_cells = 8\n{extra}")
    return cfg


def test_replay_with_a_broken_dbc(tmp_path: Path, capsys) -> None:
    dbc = tmp_path / "broken.dbc"
    dbc.write_text(DEFAULT_INPUT_DBC.read_text()[:900] + "\nBO_ 12 broken: 8 X\n SG_ oops : 0|99@9+ (\n")
    cfg = _config_file(tmp_path, dbc)
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--config", str(cfg)))
    assert_one_line_error(code, err, "dbc.input")
    assert not (tmp_path / "out.asc").exists()


def test_replay_with_a_mapped_signal_missing_from_the_dbc(tmp_path: Path, capsys) -> None:
    dbc = tmp_path / "renamed.dbc"
    dbc.write_text(DEFAULT_INPUT_DBC.read_text().replace("BMS_PackCurrent", "BMS_PackAmps"))
    cfg = _config_file(tmp_path, dbc)
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--config", str(cfg)))
    assert_one_line_error(code, err, "BMS_PackCurrent")
    assert not (tmp_path / "out.asc").exists()


@pytest.mark.parametrize("command", ["replay", "run"])
def test_binary_config_file(tmp_path: Path, capsys, command: str) -> None:
    cfg = tmp_path / "socd.toml"
    cfg.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    argv = _replay_argv(rec, tmp_path, "--config", str(cfg)) if command == "replay" else ["run", "--config", str(cfg)]
    code, err = run_cli(capsys, argv)
    assert_one_line_error(code, err, str(cfg))


@pytest.mark.parametrize("name", ["huge_temp.csv", "huge_current.csv", "huge_time.csv", "header_only.csv",
                                  "binary.csv", "nan_voltage.csv", "loaded_gap.csv"])
def test_evaluate_and_fit_refuse_bad_recordings(tmp_path: Path, capsys, name: str) -> None:
    path = BAD_RECORDINGS[name](tmp_path)
    out = tmp_path / "out.json"
    code, err = run_cli(capsys, ["evaluate", str(path), "--cell", str(DEFAULT_CELL_PROFILE), "--json", str(out),
                                 "--quiet"])
    assert_one_line_error(code, err, str(path))
    prof = tmp_path / "cell.toml"
    code, err = run_cli(capsys, ["fit", str(path), "--capacity-ah", "2.9", "-o", str(prof), "--max-seconds", "1"])
    assert_one_line_error(code, err, str(path))
    assert not out.exists() and not prof.exists()


def test_bounds_flag_narrows_the_plausible_range(tmp_path: Path, capsys, monkeypatch) -> None:
    """``--bounds`` replaces a column's range for every loader of the command: a recording inside
    the default range but outside the user's is refused with its row and field."""
    from service import validation

    monkeypatch.setattr(validation, "DEFAULT_BOUNDS", validation.DEFAULT_BOUNDS)  # restored after the test
    path = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    out = tmp_path / "out.json"
    code, err = run_cli(capsys, ["evaluate", str(path), "--cell", str(DEFAULT_CELL_PROFILE), "--json", str(out),
                                 "--quiet", "--bounds", "voltage_v=3.65:4.3"])
    assert_one_line_error(code, err, str(path))
    assert "voltage_v" in err and "row" in err and not out.exists()


@pytest.mark.parametrize("spec", ["voltage=0:5", "voltage_v=5:0", "voltage_v=0", "voltage_v=a:b", "voltage_v=0:inf"])
def test_bad_bounds_flag_is_an_argument_error(tmp_path: Path, capsys, spec: str) -> None:
    path = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", str(path), "--cell", str(DEFAULT_CELL_PROFILE), "--bounds", spec])
    assert code == 2 and "argument --bounds" in err and "Traceback" not in err, err


@pytest.mark.parametrize("table", ["nan", "binary", "duplicate", "volts_in_mv", "reversed", "past_full", "flat",
                                   "narrow"])
def test_fit_refuses_bad_ocv_tables(tmp_path: Path, capsys, table: str) -> None:
    ocv = tmp_path / f"ocv_{table}.csv"
    soc = np.linspace(0, 1, 11)
    v = 3.0 + 1.2 * soc
    if table == "binary":
        ocv.write_bytes(bytes(range(256)))
    else:
        if table == "nan":
            v[4] = np.nan
        if table == "volts_in_mv":
            v = v * 1000
        if table == "duplicate":
            soc[5] = soc[4]
        if table == "reversed":  # falls as SOC rises: the monotone fit would flatten it into a constant
            v = v[::-1]
        if table == "past_full":  # SOC to 1.2: neither fractions nor percent
            soc = soc * 1.2
        if table == "flat":  # a constant column: every SOC reads the same
            v = np.full_like(v, 3.7)
        if table == "narrow":  # SOC 0.4 to 0.6: everything else would be held flat
            soc = 0.4 + 0.2 * soc
        ocv.write_text("soc,ocv_v\n" + "\n".join(f"{s},{x}" for s, x in zip(soc, v)) + "\n")
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    prof = tmp_path / "cell.toml"
    code, err = run_cli(capsys, ["fit", str(rec), "--capacity-ah", "2.9", "--ocv", str(ocv), "-o", str(prof),
                                 "--max-seconds", "1"])
    assert_one_line_error(code, err, str(ocv))
    assert not prof.exists()


def test_fit_refuses_ocv_smoothing_with_a_given_ocv_table(tmp_path: Path, capsys) -> None:
    """--ocv-smoothing smooths a jointly fitted OCV: named with a table it would do nothing, so it is
    refused in one line and nothing is written."""
    ocv = tmp_path / "ocv.csv"
    soc = np.linspace(0, 1, 11)
    ocv.write_text("soc,ocv_v\n" + "\n".join(f"{s},{3.0 + 1.2 * s}" for s in soc) + "\n")
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    prof = tmp_path / "cell.toml"
    code, err = run_cli(capsys, ["fit", str(rec), "--capacity-ah", "2.9", "--ocv", str(ocv), "-o", str(prof),
                                 "--ocv-smoothing", "1", "--max-seconds", "1"])
    assert_one_line_error(code, err, "--ocv-smoothing")
    assert not prof.exists()


def test_header_only_csv_prints_no_numpy_warning(tmp_path: Path, capsys) -> None:
    path = BAD_RECORDINGS["header_only.csv"](tmp_path)
    code, err = run_cli(capsys, ["evaluate", str(path), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet"])
    assert_one_line_error(code, err, "needs at least 2 data rows")
    assert "Warning" not in err


def test_a_valid_log_replays(tmp_path: Path, capsys) -> None:
    """The log validation reads a python-can log python-can wrote (and counts its frames)."""
    import can

    from service.validation import check_can_log

    log = tmp_path / "cap.asc"
    with can.Logger(str(log)) as w:
        for k in range(20):
            w.on_message_received(can.Message(timestamp=1.0 + 0.01 * k, arbitration_id=0x100, data=[k] * 8,
                                              is_extended_id=False))
    assert check_can_log(log, (".asc",)) == 20
    shutil.copy(log, tmp_path / "copy.asc")
    code, err = run_cli(capsys, ["replay", str(tmp_path / "copy.asc"), "--no-send", "--record",
                                 str(tmp_path / "out.blf"), "--quiet"])
    assert code == 0, err


def _write_log(path: Path, times: list[float]) -> None:
    """A python-can log of one frame per time. python-can's ASC writer cannot write a time earlier
    than its first (it writes the distance), so an .asc is written as text, as another tool would."""
    import can

    if path.suffix == ".asc":
        rows = [f" {t:.6f} 1  100             Rx   d 8 {' '.join([f'{k % 256:02X}'] * 8)}" for k, t in enumerate(times)]
        path.write_text("date Sat Nov 28 09:28:48.549 2026\nbase hex  timestamps absolute\ninternal events logged\n"
                        "Begin Triggerblock Thu Jan 01 00:00:00.0 1970\n 0.000000 Start of measurement\n"
                        + "\n".join(rows) + "\nEnd TriggerBlock\n")
        return
    with can.Logger(str(path)) as w:
        for k, t in enumerate(times):
            w.on_message_received(can.Message(timestamp=t, arbitration_id=0x100, data=[k % 256] * 8,
                                              is_extended_id=False))


@pytest.mark.parametrize("suffix", [".csv", ".asc", ".trc"])
def test_a_log_whose_time_goes_back_is_refused(tmp_path: Path, capsys, suffix: str) -> None:
    """Two logs joined end to end: the second's frames are older than the first's. Jitter of a few ms
    between channels is not refused."""
    log = tmp_path / f"joined{suffix}"
    _write_log(log, [100.0 + 0.01 * k for k in range(20)] + [50.0 + 0.01 * k for k in range(20)])
    code, err = run_cli(capsys, ["replay", str(log), "--no-send", "--record", str(tmp_path / "out.blf"), "--quiet"])
    assert_one_line_error(code, err, str(log))
    assert "out of order" in err and "frame 21" in err, err
    jitter = tmp_path / f"jitter{suffix}"
    _write_log(jitter, [100.0 + 0.01 * k - (0.005 if k % 2 else 0.0) for k in range(20)])
    code, err = run_cli(capsys, ["replay", str(jitter), "--no-send", "--record", str(tmp_path / "out2.blf"), "--quiet"])
    assert code == 0, err


@pytest.mark.parametrize("which", ["--cell", "--settings"])
def test_binary_profile_or_settings(tmp_path: Path, capsys, which: str) -> None:
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\x00\x01\xfe" + bytes(range(256)))
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    cell = str(binary) if which == "--cell" else str(DEFAULT_CELL_PROFILE)
    argv = ["evaluate", str(rec), "--cell", cell, "--quiet"]
    if which == "--settings":
        argv += ["--settings", str(binary)]
    code, err = run_cli(capsys, argv)
    assert_one_line_error(code, err, str(binary))


def test_a_long_rest_between_samples_is_read(tmp_path: Path) -> None:
    """An OCV test logs nothing for hours while the cell rests (no current held): that is a
    recording, not a gap; the same pause under load is refused (``loaded_gap.csv``)."""
    from service.recording import load_recording

    times = [*range(30), *range(50000, 50030)]
    path = _recording(tmp_path, "rest_gap.csv", "\n".join(
        f"{t},{0.0 if 29 <= k <= 30 else 1.0},{3.7 - 0.001 * k},25.0" for k, t in enumerate(times)))
    assert len(load_recording(path)) == 60


def test_line_endings_of_any_kind_read_alike(tmp_path: Path) -> None:
    from service.recording import load_recording

    text = HEADER + "\n" + GOOD_ROWS + "\n"
    for name, ending in (("lf.csv", "\n"), ("crlf.csv", "\r\n"), ("cr.csv", "\r")):
        (tmp_path / name).write_bytes(text.replace("\n", ending).encode())
    ref = load_recording(tmp_path / "lf.csv")
    for name in ("crlf.csv", "cr.csv"):
        rec = load_recording(tmp_path / name)
        assert np.array_equal(rec.voltage_v, ref.voltage_v) and np.array_equal(rec.time_s, ref.time_s)


def _profile_with(tmp: Path, name: str, old: str, new: str) -> Path:
    text = Path(DEFAULT_CELL_PROFILE).read_text()
    assert old in text, old
    path = tmp / name
    path.write_text(text.replace(old, new, 1))
    return path


def _ocv_rows(text: str) -> str:
    """The first OCV row of the bundled profile's TOML (``ocv_v = [[...], ...]``)."""
    start = text.index("ocv_v = [") + len("ocv_v = [")
    return text[start:text.index("]", start) + 1]


@pytest.mark.parametrize("case", ["nan_ocv", "reversed_ocv", "capacity_as_text", "capacity_true",
                                  "newer_schema", "hot_point"])
def test_evaluate_refuses_a_corrupt_profile_naming_it(tmp_path: Path, capsys, case: str) -> None:
    """A profile whose numbers cannot be right is refused on load, with the file and the field, by
    every command that reads one, instead of running on a silently wrong model."""
    text = Path(DEFAULT_CELL_PROFILE).read_text()
    row = _ocv_rows(text)
    values = [v.strip() for v in row.strip().strip("[]").split(",") if v.strip()]
    edits = {
        "nan_ocv": (row, "[nan, " + ", ".join(values[1:]) + "]"),
        "reversed_ocv": (row, "[" + ", ".join(reversed(values)) + "]"),
        "capacity_as_text": ("capacity_ah = ", 'capacity_ah = "2.9"\nx_ = '),
        "capacity_true": ("capacity_ah = ", "capacity_ah = true\nx_ = "),
        "newer_schema": ("schema_version = 1", "schema_version = 99"),
        "hot_point": ("temp_c = ", "temp_c = 500.0\nx_ = "),
    }
    old, new = edits[case]
    path = _profile_with(tmp_path, f"{case}.toml", old, new)
    if case in ("capacity_as_text", "capacity_true", "hot_point"):  # drop the displaced original value
        path.write_text("\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith("x_ = ")) + "\n")
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(path), "--quiet"])
    assert_one_line_error(code, err, str(path))
    field = {"nan_ocv": "ocv.ocv_v", "reversed_ocv": "falls", "capacity_as_text": "capacity_ah",
             "capacity_true": "capacity_ah", "newer_schema": "schema_version", "hot_point": "temp_c"}[case]
    assert field in err, err


def test_fit_never_writes_over_its_own_input(tmp_path: Path, capsys) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    before = rec.read_bytes()
    twin = tmp_path / "ok.json"
    twin.write_bytes(before)
    code, err = run_cli(capsys, ["fit", str(twin), "--capacity-ah", "2.9", "-o", str(twin), "--max-seconds", "1"])
    assert_one_line_error(code, err, "is one of the input files")
    assert twin.read_bytes() == before


@pytest.mark.parametrize("flag", ["-o", "--plots"])
def test_fit_checks_where_it_writes_before_fitting(tmp_path: Path, capsys, flag: str) -> None:
    """An output that cannot be written is an argument error before the fit runs; with ``--plots``
    pointing at a file, no profile is written either."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    folder = tmp_path / "a_folder.toml"
    folder.mkdir()
    prof = tmp_path / "cell.toml"
    argv = ["fit", str(rec), "--capacity-ah", "2.9", "--max-seconds", "1"]
    argv += ["-o", str(folder)] if flag == "-o" else ["-o", str(prof), "--plots", str(rec)]
    code, err = run_cli(capsys, argv)
    assert code == 2 and f"argument {flag}" in err and "Traceback" not in err, err
    assert not prof.exists() and not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize("argv", [
    ["fit", "REC", "--capacity-ah", "2.9", "--memory-length", "100000", "-o", "cell.toml"],  # ran away unbounded
    ["evaluate", "REC", "--cell", "CELL", "--json", "FOLDER"],
    ["evaluate", "REC", "--cell", "CELL", "--traces", "REC"],
    ["diagnose", "REC", "--cell", "CELL", "--save-profile", "FOLDER"],
    ["diagnose", "REC", "--cell", "CELL", "--save-profile", "cell.txt"],
    ["demo", "--seconds", "10", "--plot", "soc.txt"],
    ["replay", "REC", "--no-send", "--cells", "8", "--spread-capacity", "0.5"],
    ["replay", "REC", "--no-send", "--cells", "8", "--spread-temperature", "500"],  # sensors at ±1500 °C
    ["replay", "REC", "--no-send", "--cells", "8", "--spread-soc", "5"],  # every cell clipped to 0 or 1
    ["replay", "REC", "--no-send", "--cells", "8", "--jitter", "1e12"],  # "year 22154 is out of range (DBC)"
    ["replay", "REC", "--no-send", "--cells", "8", "--time-offset=-1e12"],
    ["replay", "REC", "--record", "out.txt"],  # python-can writes .txt, and no reader opens it again
])
def test_output_and_spread_flags_are_checked_as_arguments(tmp_path: Path, capsys, argv: list[str]) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    (tmp_path / "folder").mkdir()
    subs = {"REC": str(rec), "CELL": str(DEFAULT_CELL_PROFILE), "FOLDER": str(tmp_path / "folder"),
            "cell.txt": str(tmp_path / "cell.txt"), "soc.txt": str(tmp_path / "soc.txt")}
    code, err = run_cli(capsys, [subs.get(a, a) for a in argv])
    assert code == 2 and "error: argument" in err and "Traceback" not in err, err


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_a_capacity_in_milliamp_hours_is_refused(tmp_path: Path, capsys, command: str) -> None:
    """Told 2900 for a 2.9 Ah cell, every current reads as a thousandth of its C-rate: `socd diagnose`
    answered none; `socd fit` refuses for want of current steps and gives the C-rate it read."""
    rows = "\n".join(f"{t},{1.0 if t % 20 < 10 else 0.0},{3.7 - 0.001 * t},25.0" for t in range(300))
    rec = _recording(tmp_path, "drive.csv", rows)
    ocv = tmp_path / "ocv.csv"
    ocv.write_text("soc,ocv_v\n" + "\n".join(f"{s:g},{3.0 + 1.2 * s:g}" for s in np.linspace(0, 1, 11)) + "\n")
    argv = {"fit": ["fit", str(rec), "--capacity-ah", "2900", "-q", "-o", str(tmp_path / "cell.toml")],
            "diagnose": ["diagnose", str(rec), "--ocv", str(ocv), "--capacity-ah", "2900"]}[command]
    code, err = run_cli(capsys, argv)
    assert_one_line_error(code, err, "drive.csv: ")
    assert "1 A, 0.00034C of --capacity-ah 2900" in err
    assert not (tmp_path / "cell.toml").exists()


def test_demo_refuses_a_recording_sampled_slower_than_the_service_steps(tmp_path: Path, capsys) -> None:
    """A time column in ms reads as samples 1000 s apart: the daemon rejected every step and the demo
    printed an RMSE of nan with exit 0."""
    rows = "\n".join(f"{1000 * t},{1.0 if t % 20 < 10 else 0.0},{3.7 - 0.001 * t},25.0" for t in range(60))
    rec = _recording(tmp_path, "ms.csv", rows)
    code, err = run_cli(capsys, ["demo", "--recording", str(rec), "--cells", "2"])
    assert_one_line_error(code, err, "ms.csv: samples every 1000 s")


@pytest.mark.parametrize("effects", [",,", ""])
def test_diagnose_refuses_an_effects_list_that_names_none(tmp_path: Path, capsys, effects: str) -> None:
    """``--effects ,,`` tried no candidate and answered none; ``--effects ""`` quietly tried all."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["diagnose", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--effects", effects])
    assert_one_line_error(code, err, "--effects names no effect")


@pytest.mark.parametrize("effects, named", [("capacity,capacity", "--effects: capacity given more than once"),
                                             ("capacity, kinetics,capacity", "--effects: capacity given more than once"),
                                             ("ocv,kinetics,ocv,kinetics", "--effects: ocv, kinetics given more than once")])
def test_diagnose_refuses_an_effect_named_twice(tmp_path: Path, capsys, effects: str, named: str) -> None:
    """``--effects capacity,capacity`` dropped the second name without a word."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["diagnose", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--effects", effects])
    assert_one_line_error(code, err, named)


def test_diagnose_names_an_unknown_effect_once(tmp_path: Path, capsys) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["diagnose", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--effects",
                                 "magic,capacity,magic"])
    assert_one_line_error(code, err, "--effects: unknown effect(s) magic; choose from")


def test_diagnose_refuses_a_capacity_it_would_ignore(tmp_path: Path, capsys) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["diagnose", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--capacity-ah", "3"])
    assert_one_line_error(code, err, "--capacity-ah goes with --ocv")


def test_diagnose_refuses_a_current_in_milliamps(tmp_path: Path, capsys) -> None:
    """A recording logged in mA, within the ±1000 plausible for amps, moves a thousand times the charge:
    more than the whole cell between its highest and lowest counted point, whatever the start."""
    rows = "\n".join(f"{t},{800.0 if t < 100 else -500.0},{3.7 - 0.001 * t},25.0" for t in range(150))
    rec = _recording(tmp_path, "milliamps.csv", rows)
    code, err = run_cli(capsys, ["diagnose", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet"])
    assert_one_line_error(code, err, str(rec))
    assert "the current's unit or the capacity" in err, err


def test_config_names_a_bad_zenoh_endpoint(tmp_path: Path, capsys) -> None:
    cfg = _config_file(tmp_path, Path(DEFAULT_INPUT_DBC), '[zenoh]\nlisten = ["not-an-endpoint"]\n')
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert code == 2 and "not-an-endpoint" in err and "Traceback" not in err, err


def test_a_column_named_twice_is_refused(tmp_path: Path, capsys) -> None:
    path = _recording(tmp_path, "two_voltages.csv", "\n".join(r + ",3.0" for r in GOOD_ROWS.split("\n")),
                      header=HEADER + ",voltage_v")
    code, err = run_cli(capsys, ["evaluate", str(path), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet"])
    assert_one_line_error(code, err, str(path))
    assert "voltage_v appears 2 times" in err


@pytest.mark.parametrize("flag, value, expected", [("--start", "100", "past the end"),
                                                   ("--stop", "0", "--stop 0 plays no frame")])
def test_replay_window_that_plays_nothing_is_refused(tmp_path: Path, capsys, flag: str, value: str,
                                                     expected: str) -> None:
    """A --start past the end, or --stop 0 (it wrote an empty log with exit 0), plays no frame."""
    path = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, _replay_argv(path, tmp_path, flag, value))
    assert_one_line_error(code, err, expected)
    assert not (tmp_path / "out.asc").exists()


def test_evaluate_refuses_traces_that_would_overwrite_each_other(tmp_path: Path, capsys) -> None:
    (tmp_path / "b").mkdir()
    one = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    two = _recording(tmp_path / "b", "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", str(one), str(two), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet",
                                 "--traces", str(tmp_path / "traces")])
    assert_one_line_error(code, err, "two recordings are named ok")
    assert not (tmp_path / "traces").exists()


@pytest.mark.parametrize("command", ["fit", "diagnose", "demo", "replay"])
def test_a_negative_seed_is_an_argument_error(tmp_path: Path, capsys, command: str) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    argv = {"fit": ["fit", str(rec), "--capacity-ah", "2.9", "-o", str(tmp_path / "c.toml")],
            "diagnose": ["diagnose", str(rec), "--cell", str(DEFAULT_CELL_PROFILE)],
            "demo": ["demo", "--seconds", "10"], "replay": _replay_argv(rec, tmp_path)}[command]
    code, err = run_cli(capsys, [*argv, "--seed", "-1"])
    assert code == 2 and "argument --seed" in err and "Traceback" not in err, err


def test_evaluate_refuses_a_truth_that_cannot_be(tmp_path: Path, capsys) -> None:
    """A current logged in mA counts a thousand times the charge: the truth SOC leaves [0, 1] within a
    minute and every score against it would be meaningless, so the recording is refused."""
    rows = "\n".join(f"{t},{1000.0 if t % 20 < 10 else 0.0},{3.7 - 0.001 * t},25.0" for t in range(60))
    path = _recording(tmp_path, "milliamps.csv", rows)
    code, err = run_cli(capsys, ["evaluate", str(path), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet",
                                 "--estimator", "coulomb"])
    assert_one_line_error(code, err, str(path))
    assert "current's unit" in err


def test_evaluate_never_writes_its_json_over_a_recording(tmp_path: Path, capsys) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    before = rec.read_bytes()
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet",
                                 "--json", str(rec)])
    assert_one_line_error(code, err, "is one of the input files")
    assert rec.read_bytes() == before


@pytest.mark.parametrize("argv", [
    ["watch", "--once", "--prefix", ""],
    ["watch", "--once", "--pack", "a//b"],
    ["bench", "--latency", "--seconds", "1e12"],
])
def test_watch_and_bench_check_their_flags(capsys, argv: list[str]) -> None:
    """A key part Zenoh refuses (a traceback from zenoh before) and a benchmark length that would
    allocate terabytes are argument errors naming the flag."""
    code, err = run_cli(capsys, argv)
    assert code == 2 and f"argument {argv[2]}" in err and "Traceback" not in err, err


@pytest.mark.parametrize("extra", [
    '[checkpoint]\npath = "FOLDER"\n',  # a folder was moved aside as an "unusable checkpoint" at start-up
    "[estimator]\nukf_kappa = nan\n",  # reset the filter at every step
    "[estimator]\nvoltage_noise_v = inf\n",
    "[estimator]\nvoltage_noise_v = 1e300\n",  # squared, it overflowed at start-up
    "[output]\ncan_period_s = inf\n",
])
def test_config_refuses_settings_that_cannot_be(tmp_path: Path, capsys, extra: str) -> None:
    (tmp_path / "folder").mkdir()
    cfg = _config_file(tmp_path, Path(DEFAULT_INPUT_DBC), extra.replace("FOLDER", str(tmp_path / "folder")))
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert code == 2 and "Traceback" not in err, err
    assert (tmp_path / "folder").is_dir()


@pytest.mark.parametrize("extra", [
    '[zenoh]\nlisten = ["tcp/127.0.0.1:70000"]\n',
    '[mapping]\ncell_voltage_pattern = "BMS_Cell{number:0999999999d}_V"\n',  # hung socd check building names
    # a width read from the cell number: 888 characters for cell 8, 100 million for cell 100
    '[mapping]\ncell_voltage_pattern = "BMS_Cell{number:0{number}{number}{number}d}_V"\n',
])
def test_config_refuses_a_port_or_pattern_that_cannot_work(tmp_path: Path, capsys, extra: str) -> None:
    cfg = _config_file(tmp_path, Path(DEFAULT_INPUT_DBC), extra)
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert code == 2 and ("70000" in err or "field width" in err or "field of its own" in err), err
    assert "Traceback" not in err, err


@pytest.mark.parametrize("flag", ["--min-order", "--min-slow-order"])
@pytest.mark.parametrize("value", ["1.0", "0", "nan"])
def test_fit_refuses_an_order_bound_the_search_cannot_hold(tmp_path: Path, capsys, flag: str, value: str) -> None:
    """An order bound of 1 or more left the search an empty range and failed only after the OCV was
    fitted; it is an argument error naming the flag, before any file is read."""
    code, err = run_cli(capsys, ["fit", str(tmp_path / "never_read.csv"), "--capacity-ah", "2", flag, value,
                                 "-o", str(tmp_path / "cell.toml")])
    assert code == 2 and f"argument {flag}" in err and "Traceback" not in err, err
    assert not (tmp_path / "cell.toml").exists()


@pytest.mark.parametrize("value", ["1.5", "-0.1", "nan"])
def test_fit_refuses_a_pure_ohmic_share_outside_zero_to_one(tmp_path: Path, capsys, value: str) -> None:
    code, err = run_cli(capsys, ["fit", str(tmp_path / "never_read.csv"), "--capacity-ah", "2",
                                 "--pure-ohmic-share", value, "-o", str(tmp_path / "cell.toml")])
    assert code == 2 and "argument --pure-ohmic-share" in err and "Traceback" not in err, err
    assert not (tmp_path / "cell.toml").exists()


def test_config_with_a_byte_order_mark_is_read(tmp_path: Path, capsys) -> None:
    cfg = _config_file(tmp_path, Path(DEFAULT_INPUT_DBC))
    cfg.write_bytes(b"\xef\xbb\xbf" + cfg.read_bytes())
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert code == 0, err


def test_watch_checks_its_endpoint(capsys) -> None:
    code, err = run_cli(capsys, ["watch", "--once", "--connect", "tcp/127.0.0.1:99999"])
    assert code == 2 and "argument --connect" in err and "99999" in err, err


def test_replay_names_the_dbc_when_a_signal_cannot_carry_its_values(tmp_path: Path, capsys) -> None:
    """A cell-voltage signal one bit wide cannot carry 3.7 V: the replay stops naming the message and
    the input DBC (it blamed the recording before), and writes no log."""
    text = DEFAULT_INPUT_DBC.read_text()
    old = "SG_ BMS_Cell001_V m0 : 12|13@1+"
    assert old in text
    dbc = tmp_path / "narrow.dbc"
    dbc.write_text(text.replace(old, "SG_ BMS_Cell001_V m0 : 12|1@1+"))
    cfg = _config_file(tmp_path, dbc)
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--config", str(cfg), "--cells", "8"))
    assert_one_line_error(code, err, str(dbc))
    assert "BMS_CellVoltages" in err and not (tmp_path / "out.asc").exists()


def test_replay_counts_values_it_clips_to_a_signals_declared_range(tmp_path: Path, capsys) -> None:
    """A DBC whose current signal declares ±0.5 A gets the recording's 1 A clipped; the replay says
    so with the count per signal instead of sending the clipped current silently."""
    text = DEFAULT_INPUT_DBC.read_text()
    old = "[-1638.4|1638.35]"
    assert old in text
    dbc = tmp_path / "clipped.dbc"
    dbc.write_text(text.replace(old, "[-0.5|0.5]", 1))
    cfg = _config_file(tmp_path, dbc)
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--config", str(cfg), "--cells", "8"))
    amps = sum(1 for t in range(60) if t % 20 < 10)
    assert code == 0, err
    assert f"BMS_PackCurrent {amps}x" in err and str(dbc) in err, err
    assert (tmp_path / "out.asc").exists()
    # the shipped DBC carries the same recording without a word about clipping
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--config", str(_config_file(tmp_path, DEFAULT_INPUT_DBC)),
                                             "--cells", "8"))
    assert code == 0 and "clipped" not in err, err


def test_fit_with_a_capacity_a_thousand_times_too_large_names_it(tmp_path: Path, capsys) -> None:
    """Every C-rate rule reads the current through the capacity: the refusal shows the C-rate it read."""
    calce = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "calce_inr18650_20r"
    rec = calce / "calce20r_25C_DST_80soc.csv"
    out = tmp_path / "cell.toml"
    code, err = run_cli(capsys, ["fit", str(rec), "--full-at", "3303", "--capacity-ah", "2000", "-q", "-o", str(out)])
    assert code == 2 and "--capacity-ah 2000" in err and "0.002C" in err, err
    assert not out.exists()


@pytest.mark.parametrize("command", ["fit", "evaluate", "diagnose", "demo", "replay"])
def test_a_current_logged_with_charge_positive_is_refused(tmp_path: Path, capsys, command: str) -> None:
    """The bundled US06 with its current negated (a logger that counts charge positive): the voltage
    jumps up at every large current step, which a cell's ohmic drop never does in socd's convention.
    Each command says so in one line; ``socd diagnose``, which has no full point to count from, ran
    on it before and blamed the model."""
    from service.assets import bundled_recording
    from service.recording import load_recording, save_recording

    rec = load_recording(bundled_recording())
    flipped = save_recording(tmp_path / "flipped.csv", np.column_stack(
        [rec.time_s, -rec.current_a, rec.voltage_v, rec.temperature_c]))
    argv = {"fit": ["fit", str(flipped), "--capacity-ah", "2.77", "-o", str(tmp_path / "cell.toml")],
            "evaluate": ["evaluate", "--cell", str(DEFAULT_CELL_PROFILE), str(flipped), "-q"],
            "diagnose": ["diagnose", str(flipped), "--cell", str(DEFAULT_CELL_PROFILE)],
            "demo": ["demo", "--recording", str(flipped), "--cells", "2", "--seconds", "60"],
            "replay": ["replay", str(flipped), "--no-send", "--record", str(tmp_path / "out.asc"), "-q"]}[command]
    code, err = run_cli(capsys, argv)
    assert_one_line_error(code, err, "flipped.csv: the voltage jumps up where the current steps up")
    assert "negate current_a" in err and not (tmp_path / "cell.toml").exists() and not (tmp_path / "out.asc").exists()


def test_no_shared_recording_looks_logged_charge_positive() -> None:
    """The sign test on every shared real and labelled recording: none is flagged, and each drive with
    its current negated is (an OCV test's few steps are left alone)."""
    from dataclasses import replace

    from service.cell.truth import SIGN_AGREEMENT, SIGN_MIN_STEPS, current_sign_steps
    from service.recording import load_recording

    shared = Path(__file__).resolve().parents[2] / "shared" / "data"
    files = sorted(shared.glob("real/*/*.csv")) + sorted(shared.glob("synthetic/*.csv"))
    if not files:
        pytest.skip("../shared/data is not here")
    flagged = 0
    for path in files:
        if "soc_table" in path.name or (path.parent.name == "synthetic" and path.stem.endswith("_ocv")):
            continue  # OCV tables beside the recordings
        rec = load_recording(path)
        up, steps = current_sign_steps(rec)
        assert steps < SIGN_MIN_STEPS or up <= SIGN_AGREEMENT * steps, path.name
        up, steps = current_sign_steps(replace(rec, current_a=-rec.current_a))
        flagged += steps >= SIGN_MIN_STEPS and up > SIGN_AGREEMENT * steps
    assert flagged >= 60, flagged


def test_diagnose_refuses_a_voltage_that_never_moves(tmp_path: Path, capsys) -> None:
    """A stuck voltage channel (the bundled drive with its voltage held at 3.9 V): a synthetic DST so
    diagnosed named capacity with exit 0. No shared recording has a large current step the voltage
    stays put at everywhere."""
    from dataclasses import replace

    from service.assets import bundled_recording
    from service.cell.truth import check_voltage_moves
    from service.recording import load_recording, save_recording

    rec = load_recording(bundled_recording())
    check_voltage_moves(rec)
    stuck = save_recording(tmp_path / "stuck.csv", np.column_stack(
        [rec.time_s, rec.current_a, np.full(len(rec), 3.9), rec.temperature_c]))
    code, err = run_cli(capsys, ["diagnose", str(stuck), "--cell", str(DEFAULT_CELL_PROFILE), "-q"])
    assert_one_line_error(code, err, f"{stuck}: the voltage does not move at any of its ")
    shared = Path(__file__).resolve().parents[2] / "shared" / "data"
    for path in sorted(shared.glob("real/*/*.csv")) + sorted(shared.glob("synthetic/*.csv")):
        if "soc_table" not in path.name and not path.stem.endswith("_ocv"):
            rec = load_recording(path)
            check_voltage_moves(rec)
            check_voltage_moves(replace(rec, voltage_v=np.round(rec.voltage_v, 2)))  # written to 10 mV


def _drive_with_a_pause(tmp_path: Path, pause_s: int) -> tuple[Path, float]:
    """The bundled US06 with ``pause_s`` of rows cut out where the current resumes under load (a logger
    that lost them): the sample after the pause holds its current over the whole pause."""
    from service.assets import bundled_recording
    from service.recording import load_recording, save_recording

    rec = load_recording(bundled_recording())
    # a pause that ends on the drive's first sample above 5 A after 2000 s
    end = int(np.argmax((rec.time_s > 2000.0) & (rec.current_a > 5.0)))
    keep = (rec.time_s <= rec.time_s[end] - pause_s) | (np.arange(len(rec)) >= end)
    path = save_recording(tmp_path / "paused.csv", np.column_stack(
        [rec.time_s[keep], rec.current_a[keep], rec.voltage_v[keep], rec.temperature_c[keep]]))
    return path, float(rec.current_a[end])


@pytest.mark.parametrize("command", ["fit", "evaluate", "diagnose"])
def test_a_pause_in_the_logging_under_load_is_refused(tmp_path: Path, capsys, command: str) -> None:
    """Five minutes of a drive not logged: the truth and every filter held the resumed 5.8 A over the
    pause, and `socd evaluate` scored the estimators 0.50 -> 2.9 % against that truth with exit 0."""
    paused, resumed_a = _drive_with_a_pause(tmp_path, 300)
    argv = {"fit": ["fit", str(paused), "--capacity-ah", "2.77", "-q", "-o", str(tmp_path / "cell.toml")],
            "evaluate": ["evaluate", "--cell", str(DEFAULT_CELL_PROFILE), str(paused), "-q"],
            "diagnose": ["diagnose", str(paused), "--cell", str(DEFAULT_CELL_PROFILE)]}[command]
    code, err = run_cli(capsys, argv)
    assert_one_line_error(code, err, "paused.csv: time_s jumps by 300 s after ")
    assert f"to {round(resumed_a, 4):g} A" in err and "split the recording there" in err  # as saved: 4 decimals
    assert not (tmp_path / "cell.toml").exists()


def _constant_current_with_a_hole(tmp_path: Path, hole_s: int) -> Path:
    """A minute's rest, then 2.77 A for 3000 s logged every second, with ``hole_s`` of rows lost from
    its middle: the same current on both sides of the hole."""
    t = np.arange(0, 3060)
    keep = (t < 1500) | (t >= 1500 + hole_s)
    i = np.where(t < 60, 0.0, 2.77)
    v = np.where(t < 60, 4.1, 4.0 - 0.5 * (t - 60) / 3000)
    return _recording(tmp_path, "cc_hole.csv", "\n".join(f"{a},{b:g},{c:.4f},25.0" for a, b, c in
                                                         zip(t[keep], i[keep], v[keep])))


@pytest.mark.parametrize("command", ["fit", "evaluate", "diagnose"])
def test_rows_lost_from_a_constant_current_stretch_are_refused(tmp_path: Path, capsys, command: str) -> None:
    """20 minutes cut out of a 1C stretch logged every second: the current is the same on both sides, so
    the hole passed as sparse logging, 33 % of the capacity was counted that never flowed in the file,
    and `socd diagnose` fitted a base model 1 V off on the held-out part of such a pulse test and named
    capacity."""
    path = _constant_current_with_a_hole(tmp_path, 1200)
    argv = {"fit": ["fit", str(path), "--capacity-ah", "2.77", "-q", "-o", str(tmp_path / "cell.toml")],
            "evaluate": ["evaluate", "--cell", str(DEFAULT_CELL_PROFILE), str(path), "-q"],
            "diagnose": ["diagnose", str(path), "--cell", str(DEFAULT_CELL_PROFILE), "-q"]}[command]
    code, err = run_cli(capsys, argv)
    assert_one_line_error(code, err, "cc_hole.csv: time_s jumps by 1201 s after 1499 s under 2.77 A, amid samples 1 s")
    assert "split the recording there" in err and not (tmp_path / "cell.toml").exists()


def test_pauses_at_rest_and_in_a_constant_current_stretch_are_not_refused() -> None:
    """Sparse logging is not a gap: a pulse test logged every 300 s at rest (its next pulse held over the
    last pause, as the Panasonic and PyBaMM pulse tests here have it), a C/20 discharge logged every
    600 s, and every shared recording pass."""
    from service.cell.truth import unlogged_charge
    from service.recording import Recording, load_recording

    t = np.concatenate([np.arange(0.0, 100.0), 100.0 + 300.0 * np.arange(1, 5), np.arange(1300.0, 1400.0)])
    i = np.where((t < 50) | (t >= 1300), 3.0, 0.0)  # a pulse, rest logged sparsely, the next pulse
    rest = Recording(Path("rest.csv"), t, i, np.full(t.size, 3.7), np.full(t.size, 25.0))
    assert unlogged_charge(rest, 2.77, "c") is None
    t = 600.0 * np.arange(60)
    cc = Recording(Path("cc.csv"), t, np.full(t.size, 0.14), np.linspace(4.1, 3.0, t.size), np.full(t.size, 25.0))
    assert unlogged_charge(cc, 2.77, "c") is None
    # the same C/20 stretch after a drive logged every second: its pauses are amid pauses as long
    t = np.concatenate([np.arange(0.0, 3600.0), 3600.0 + 600.0 * np.arange(60)])
    i = np.where(t < 3600, 2.0 * np.sin(t / 20.0) ** 2, 0.14)
    mixed = Recording(Path("mixed.csv"), t, i, np.linspace(4.1, 3.0, t.size), np.full(t.size, 25.0))
    assert unlogged_charge(mixed, 2.77, "c") is None

    shared = Path(__file__).resolve().parents[2] / "shared" / "data"
    files = [p for p in sorted(shared.glob("real/*/*.csv")) + sorted(shared.glob("synthetic/*.csv"))
             if "soc_table" not in p.name and not (p.parent.name == "synthetic" and p.stem.endswith("_ocv"))]
    if not files:
        pytest.skip("../shared/data is not here")
    capacity_ah = {"pan18650pf": 2.77, "calce20r": 1.999, "calce_a123": 1.041}  # the cells' own (READMEs)
    for path in files:
        cap = next((c for prefix, c in capacity_ah.items() if path.name.startswith(prefix)), 1.0)
        assert unlogged_charge(load_recording(path), cap, "c") is None, path.name


def test_fit_refuses_a_diffusion_cap_below_the_2rc_fast_bound(tmp_path: Path, capsys) -> None:
    """``--max-tau-df 0.001`` made the diffusion branch a resistor, and the profile kept the 2-RC
    start's τ2 of hundreds of seconds anyway."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["fit", str(rec), "--capacity-ah", "2.9", "--max-tau-df", "0.001",
                                 "-o", str(tmp_path / "cell.toml")])
    assert_one_line_error(code, err, "--max-tau-df 0.001: the cap must be at least 1 s")
    assert not (tmp_path / "cell.toml").exists()


@pytest.mark.parametrize("temp_c, warned", [(-45.0, True), (-31.0, True), (-29.0, False), (25.0, False),
                                             (34.0, False), (36.0, True)])
def test_a_recording_beyond_the_profiles_temperatures_is_named(tmp_path: Path, capsys, temp_c: float,
                                                                warned: bool) -> None:
    """The bundled profile is fitted at -20 to 25 °C. A -45 °C log was scored and diagnosed on
    extrapolated parameters without a word. Within 10 K of the fitted range there is nothing to say:
    the bundled 25 °C drive heats the cell to 33 °C."""
    # opens at rest: a recording that opens under load is warned of for its initial SOC too
    rows = "\n".join(f"{t},{0.0 if t % 60 < 30 else 1.0},{4.0 - 0.0003 * t},{temp_c}" for t in range(300))
    rec = _recording(tmp_path, "cold.csv", rows)
    for argv in (["evaluate", str(rec), "--cell", "panasonic_18650pf", "--estimator", "coulomb", "--no-bar", "-q"],
                 ["diagnose", str(rec), "--cell", "panasonic_18650pf", "--effects", "capacity", "-q"]):
        code, err = run_cli(capsys, argv)
        assert code == 0, err
        warning = [ln for ln in err.splitlines() if "warning" in ln]
        if warned:
            assert len(warning) == 1 and f"cold.csv: recorded at {temp_c:.0f} °C (median)" in warning[0], err
            assert "-20 to 25 °C profile 'panasonic_18650pf'" in warning[0], err
        else:
            assert warning == [], err


def _config_with(tmp_path: Path, body: str, name: str = "c.toml") -> Path:
    cfg = tmp_path / name
    cfg.write_text(f'cell_profile = "{DEFAULT_CELL_PROFILE}"\n' + body)
    return cfg


@pytest.mark.parametrize("command", ["check", "run"])
def test_a_checkpoint_path_onto_another_file_is_refused_and_the_file_kept(tmp_path: Path, capsys,
                                                                          command: str) -> None:
    """`socd check` said OK to a checkpoint path naming the config itself, and `socd run` then moved the
    config aside as an unusable checkpoint (a recording named there went the same way)."""
    cfg = tmp_path / "self.toml"
    cfg.write_text(f'cell_profile = "{DEFAULT_CELL_PROFILE}"\n[bus]\ninterface = "virtual"\n'
                   f'channel = "ckpt-{os.getpid()}"\n[checkpoint]\npath = "{cfg}"\n')
    before = cfg.read_bytes()
    code, err = run_cli(capsys, [command, "--config", str(cfg)])
    assert_one_line_error(code, err, f"{cfg} is an existing file that is not a socd checkpoint")
    assert cfg.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["self.toml"]


def test_a_real_checkpoint_file_at_the_path_is_accepted(tmp_path: Path, capsys) -> None:
    from service.daemon.checkpoint import encode_checkpoint

    ckpt = tmp_path / "state.ckpt"
    ckpt.write_bytes(encode_checkpoint({"soc": np.zeros(2)}, {"t_s": 0.0}))
    cfg = _config_with(tmp_path, f'[checkpoint]\npath = "{ckpt}"\n')
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert code == 0, err


@pytest.mark.parametrize("where", ["proc", "under_a_file"])
def test_a_checkpoint_path_the_service_cannot_write_is_named_by_check(tmp_path: Path, capsys, where: str) -> None:
    """`socd check` said OK to a checkpoint under /proc (as root too: permission bits let root write
    anywhere, the file system does not) and under a path whose folder is a file; `socd run` then
    estimated for hours and lost its state at every restart."""
    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    path = {"proc": Path("/proc/socd-test/state.npz"), "under_a_file": a_file / "state.npz"}[where]
    cfg = _config_with(tmp_path, f'[checkpoint]\npath = "{path}"\n')
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert_one_line_error(code, err, "c.toml: checkpoint.path: ")
    assert str(path) in err and sorted(p.name for p in tmp_path.iterdir()) == ["c.toml", "notes.txt"]


def test_an_unknown_override_far_from_every_field_suggests_none(caplog, monkeypatch, capsys) -> None:
    """`SOCD_FOO` was asked whether it meant `SOCD_ZENOH`."""
    monkeypatch.setenv("SOCD_FOO", "1")
    with caplog.at_level("WARNING", logger="service.config"):
        code, err = run_cli(capsys, ["check"])
    assert code == 0, err
    assert "SOCD_FOO sets no config field; it is ignored" in caplog.text and "did you mean" not in caplog.text


def test_a_checkpoint_path_from_the_environment_is_named_as_the_environments(capsys, monkeypatch) -> None:
    monkeypatch.setenv("SOCD_CHECKPOINT__PATH", "/proc/socd-test/x.npz")
    code, err = run_cli(capsys, ["check"])
    assert_one_line_error(code, err, "checkpoint.path: cannot create files or folders in /proc")
    assert "(the path is SOCD_CHECKPOINT__PATH's, which overrides the file)" in err


def test_check_leaves_no_probe_file_in_a_writable_checkpoint_folder(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "state"
    folder.mkdir()
    cfg = _config_with(tmp_path, f'[checkpoint]\npath = "{folder / "s.npz"}"\n')
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert code == 0, err
    assert list(folder.iterdir()) == []


@pytest.mark.parametrize("section, field", [("mapping", "current_sign"), ("pack", "n_cells"),
                                            ("estimator", "memory_length"), ("bus", "max_open_retries")])
def test_a_boolean_for_a_number_in_a_config_is_refused(tmp_path: Path, capsys, section: str, field: str) -> None:
    """pydantic read `current_sign = true` as +1 (the current convention flipped) and `n_cells = true`
    as a one-cell pack; `socd check` said OK to both."""
    cfg = _config_with(tmp_path, f"[{section}]\n{field} = true\n")
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert_one_line_error(code, err, f"c.toml: {section}: {field} = true: a number is expected, not a boolean")


def test_a_boolean_field_still_takes_a_boolean_and_a_profile_refuses_one_for_a_number(tmp_path: Path,
                                                                                      capsys) -> None:
    code, err = run_cli(capsys, ["check", "--config", str(_config_with(tmp_path, "[bus]\nfd = true\n"))])
    assert code == 0, err
    text = DEFAULT_CELL_PROFILE.read_text()
    prof = tmp_path / "p.toml"
    prof.write_text("\n".join("capacity_ah = true" if ln.startswith("capacity_ah =") else ln
                              for ln in text.splitlines()) + "\n")
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", "--cell", str(prof), str(rec)])
    assert_one_line_error(code, err, "p.toml: capacity_ah = true: a number is expected, not a boolean")


def test_a_boolean_inside_a_list_of_numbers_is_refused(tmp_path: Path, capsys) -> None:
    """`voltage_range_v = [true, 4.8]` read as a range from 1 V, and an OCV row with `true` in it as a
    row through 1 V; both passed."""
    cfg = _config_with(tmp_path, "[mapping]\nvoltage_range_v = [true, 4.8]\n")
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert_one_line_error(code, err, "c.toml: mapping: voltage_range_v: numbers are expected, and it holds a boolean")
    prof = tmp_path / "p.toml"
    text = DEFAULT_CELL_PROFILE.read_text()
    start = text.index("soc = [") + len("soc = [")
    prof.write_text(text[:start] + "true, " + text[text.index(",", start) + 1:])
    code, err = run_cli(capsys, ["evaluate", "--cell", str(prof), str(_recording(tmp_path, "ok.csv", GOOD_ROWS))])
    assert_one_line_error(code, err, "soc: numbers are expected, and it holds a boolean")


#: a bus that cannot open, given up at once: were the config accepted, `socd run` would exit 1, not hang
_DEAD_BUS = ('[bus]\ninterface = "socketcan"\nchannel = "socdnosuch0"\nmax_open_retries = 1\n'
             "reconnect_initial_s = 0.05\n")


@pytest.mark.parametrize("command", ["check", "run"])
@pytest.mark.parametrize("field, value, names", [
    ("voltage_range_v", "[4.8, 4.8]", "mapping.voltage_range_v: must be [low, high] with low < high, got [4.8, 4.8]"),
    ("voltage_range_v", "[-5.0, -1.0]", "mapping.voltage_range_v: [-5.0, -1.0] lies wholly outside 0.5 to 6 V"),
    ("voltage_range_v", "[1500.0, 4800.0]", "mapping.voltage_range_v: [1500.0, 4800.0] lies wholly outside"),
    ("temperature_range_c", "[233.0, 363.0]", "mapping.temperature_range_c: [233.0, 363.0] lies wholly outside"),
    ("current_range_a", "[5.0, 1000.0]", "mapping.current_range_a: [5.0, 1000.0] leaves out 0 A"),
])
def test_a_plausibility_range_that_rejects_every_value_is_refused(tmp_path: Path, capsys, command: str,
                                                                   field: str, value: str, names: str) -> None:
    """`socd check` said OK to a voltage range below 0 V (or in mV, a temperature range in K, a current
    range leaving out rest): the decoder then counted every value out of range."""
    cfg = _config_with(tmp_path, f"{_DEAD_BUS}[mapping]\n{field} = {value}\n")
    code, err = run_cli(capsys, [command, "--config", str(cfg)])
    assert_one_line_error(code, err, f"c.toml: {names}")


def test_a_narrowed_plausibility_range_is_still_accepted(tmp_path: Path, capsys) -> None:
    cfg = _config_with(tmp_path, "[mapping]\nvoltage_range_v = [5.5, 7.0]\ntemperature_range_c = [-80.0, -50.0]\n"
                                 "current_range_a = [-5.0, 0.0]\n")
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert code == 0, err


@pytest.mark.parametrize("endpoint", ["tcp/127.0.0.1", "tcp/localhost:7447x", "tcp/127.0.0.1:-1"])
def test_a_zenoh_endpoint_without_a_numeric_port_is_refused(tmp_path: Path, capsys, endpoint: str) -> None:
    """`socd check` said OK and `socd run` retried for ever on Zenoh's "invalid port value", naming
    neither the field nor the endpoint; `socd watch` waited and blamed the service."""
    cfg = _config_with(tmp_path, f'[zenoh]\nlisten = ["{endpoint}"]\n')
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert_one_line_error(code, err, f"c.toml: zenoh.listen: '{endpoint}': a tcp endpoint needs a numeric port")
    code, err = run_cli(capsys, ["watch", "--once", "--timeout", "1", "--connect", endpoint])
    assert code == 2 and "argument --connect" in err and "numeric port" in err, err


@pytest.mark.parametrize("field", ["can_period_s", "zenoh_period_s"])
def test_a_publication_period_under_a_millisecond_is_refused(tmp_path: Path, capsys, field: str) -> None:
    """At 1e-9 s the publishing loop spun a core doing nothing."""
    cfg = _config_with(tmp_path, f"[output]\n{field} = 1e-9\n")
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert_one_line_error(code, err, f"c.toml: output.{field}: Input should be greater than or equal to 0.001")


def test_a_bad_bitrate_flag_is_named_in_one_line(capsys) -> None:
    """`socd run -i virtual -b 0` printed pydantic's multi-line dump, which never named -b/--bitrate."""
    code, err = run_cli(capsys, ["run", "-i", "virtual", "-c", f"bitrate-{os.getpid()}", "-b", "0"])
    assert_one_line_error(code, err, "argument -b/--bitrate: Input should be greater than 0, got 0")


@pytest.mark.parametrize("body, names", [
    ('[pack]\nn_cells = 8\n[mapping]\ncounter_signals = {BMS_PackStatus = "BMS_PackCurrent"}\n',
     "c.toml: mapping.counter_signals.BMS_PackStatus: signal 'BMS_PackCurrent' is a measurement"),
    ('[pack]\nn_cells = 2\n[mapping]\ntemperature_signals = [{signal = "BMS_Temp01_C", cells = [0, 0, 1]}]\n',
     "c.toml: mapping.temperature_signals[0].cells: cell 0 is listed twice"),
])
def test_a_counter_on_a_measurement_and_a_cell_listed_twice_are_refused(tmp_path: Path, capsys, body: str,
                                                                        names: str) -> None:
    """A counter mapped onto the pack current passed `socd check`, and `socd replay` wrote its count into
    the current field; a cell listed twice under one sensor passed too."""
    code, err = run_cli(capsys, ["check", "--config", str(_config_with(tmp_path, body))])
    assert_one_line_error(code, err, names)


def test_replay_refuses_a_stuck_cell_beyond_the_pack_it_replays(tmp_path: Path, capsys) -> None:
    """``--cells 4 --stuck-cell 6`` on the 8-cell default config was checked against the config only:
    the fault hit a cell that was never sent, and the replay said nothing."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["replay", str(rec), "--no-send", "--cells", "4", "--stuck-cell", "6",
                                 "--record", str(tmp_path / "out.asc")])
    assert_one_line_error(code, err, "--stuck-cell 6: the replayed pack has 4 cells")
    assert not (tmp_path / "out.asc").exists()


@pytest.mark.parametrize("command", [["demo", "--seconds", "10"], ["bench", "--latency", "--seconds", "1"]])
def test_a_misspelt_override_inside_a_section_stops_every_command_in_one_line(capsys, monkeypatch, caplog,
                                                                              command: list[str]) -> None:
    """`SOCD_BUS__CHANEL=can0` crashed `socd demo` and `socd bench --latency` with a traceback, after a
    warning that said the variable was ignored (`check`, `run` and `replay` refused it)."""
    monkeypatch.setenv("SOCD_BUS__CHANEL", "can0")
    with caplog.at_level("WARNING", logger="service.config"):
        code, err = run_cli(capsys, command)
    assert_one_line_error(code, err, "bus.chanel: unknown key (did you mean channel?)")
    assert "SOCD_BUS__CHANEL sets no config field of [bus], which refuses it (did you mean SOCD_BUS__CHANNEL?)" \
        in caplog.text


def test_an_environment_override_is_named_when_misspelt_or_bad(tmp_path: Path, capsys, monkeypatch, caplog) -> None:
    """`SOCD_PAK__N_CELLS=3` was ignored without a word, and a bad `SOCD_PACK__N_CELLS=0` was reported
    against the config file alone."""
    monkeypatch.setenv("SOCD_PAK__N_CELLS", "3")
    with caplog.at_level("WARNING", logger="service.config"):
        code, err = run_cli(capsys, ["check"])
    assert code == 0, err
    assert "SOCD_PAK__N_CELLS sets no config field; it is ignored (did you mean SOCD_PACK__N_CELLS?)" in caplog.text
    monkeypatch.delenv("SOCD_PAK__N_CELLS")
    monkeypatch.setenv("SOCD_PACK__N_CELLS", "0")
    code, err = run_cli(capsys, ["check"])
    assert_one_line_error(code, err, "pack.n_cells: Input should be greater than or equal to 1 "
                                     "(the environment overrides the file: SOCD_PACK__N_CELLS)")


@pytest.mark.parametrize("value, shown", [('"3.7"', "'\"3.7\"'"), ("3_7", "'3_7'"), ("３.７", "'３.７'")])
def test_a_number_the_reader_cannot_take_is_named_with_its_row(tmp_path: Path, capsys, value: str, shown: str) -> None:
    """Quotes, digit separators and non-ASCII digits: Python's float() takes the last two, the CSV reader
    takes none, so the message names the row and the value instead of 'a row could not be read'."""
    rec = _with(tmp_path, "odd.csv", 4, 2, value)
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet"])
    assert_one_line_error(code, err, f"odd.csv: row 6: voltage_v: {shown} is not a plain number")


def test_evaluate_writes_no_plot_or_trace_when_a_later_recording_is_refused(tmp_path: Path, capsys) -> None:
    """The truth of every recording is checked before the first is run: the good first file's traces
    are not left behind when the second's truth cannot be."""
    good = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    rows = "\n".join(f"{t},{1000.0 if t % 20 < 10 else 0.0},{3.7 - 0.001 * t},25.0" for t in range(60))
    bad = _recording(tmp_path, "milliamps.csv", rows)
    code, err = run_cli(capsys, ["evaluate", str(good), str(bad), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet",
                                 "--estimator", "coulomb", "--traces", str(tmp_path / "tr")])
    assert_one_line_error(code, err, "milliamps.csv")
    assert not (tmp_path / "tr").exists() or not any((tmp_path / "tr").iterdir())


def test_evaluate_never_writes_traces_over_a_recording(tmp_path: Path, capsys) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    other = _recording(tmp_path, "ok_traces.csv", GOOD_ROWS)
    before = other.read_bytes()
    code, err = run_cli(capsys, ["evaluate", str(rec), str(other), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet",
                                 "--estimator", "coulomb", "--traces", str(tmp_path)])
    assert_one_line_error(code, err, "--traces")
    assert other.read_bytes() == before


@pytest.mark.parametrize("command", ["diagnose", "replay"])
def test_two_outputs_onto_one_file_are_refused(tmp_path: Path, capsys, command: str) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    same = str(tmp_path / ("same.json" if command == "diagnose" else "same.csv"))
    argv = {"diagnose": ["diagnose", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--json", same,
                         "--save-profile", same],
            "replay": ["replay", str(rec), "--no-send", "--quiet", "--record", same, "--truth-out", same]}[command]
    code, err = run_cli(capsys, argv)
    assert_one_line_error(code, err, "give each output a file of its own")
    assert not Path(same).exists()


def test_demo_refuses_a_recording_outside_what_the_service_reads(tmp_path: Path, capsys) -> None:
    """A temperature of -45 °C passes the recording's plausibility range but not the -40 °C the
    service decodes from the bus: every sample was counted out of range and the demo wrote a JSON
    of NaNs with exit 1."""
    rows = "\n".join(f"{t},{1.0 if t % 20 < 10 else 0.0},{3.7 - 0.001 * t},-45.0" for t in range(60))
    rec = _recording(tmp_path, "cold.csv", rows)
    out = tmp_path / "demo.json"
    code, err = run_cli(capsys, ["demo", "--recording", str(rec), "--cells", "2", "--json", str(out)])
    assert_one_line_error(code, err, "cold.csv: row 2: temperature_c: -45 is outside")
    assert "mapping.temperature_range_c" in err and not out.exists()


@pytest.mark.parametrize("edit, field", [
    (("capacity_ah = ", "capacity_ah = 1e9\nx_ = "), "capacity_ah"),
    (("r_ohm = ", "r_ohm = 1e6\nx_ = "), "r_ohm"),
    (("capacity_scale = 1.0", "capacity_scale = 1e6"), "capacity_scale"),
    (("current_bias_a = 0.0", "current_bias_a = 1e9"), "current_bias_a"),
])
def test_a_profile_value_no_cell_can_have_is_refused(tmp_path: Path, capsys, edit: tuple[str, str], field: str) -> None:
    """A hand-edited profile with a value no lithium cell has (a 1e9 A sensor offset, a 1 MΩ resistance)
    ran to a voltage RMSE of 2e11 mV with exit 0; it is refused on load, naming the field."""
    path = _profile_with(tmp_path, "odd.toml", *edit)
    path.write_text("\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith("x_ = ")) + "\n")
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(path), "--quiet", "--estimator", "coulomb"])
    assert_one_line_error(code, err, str(path))
    assert field in err, err


@pytest.mark.parametrize("suffix", [".asc", ".blf"])
def test_a_log_cut_short_replays_with_a_warning(tmp_path: Path, capsys, suffix: str) -> None:
    """A log cut short (an ASC log without its closing 'End TriggerBlock', a BLF file smaller than its
    header states) replays the frames it has, and says so; a whole one says nothing."""
    whole = tmp_path / f"whole{suffix}"
    _write_log(whole, [1.0 + 0.1 * k for k in range(300)])
    cut = tmp_path / f"cut{suffix}"
    if suffix == ".asc":
        cut.write_text(whole.read_text().split("End TriggerBlock")[0].rsplit("\n", 3)[0] + "\n")
    else:
        cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 2 // 3])
    for path, warned in ((whole, False), (cut, True)):
        code, err = run_cli(capsys, ["replay", str(path), "--no-send", "--fast", "--quiet"])
        assert code == 0, err
        assert ("may have been cut short" in err) is warned, err


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs Linux's /dev/full (a device that is always full)")
def test_a_json_that_cannot_be_written_is_named(tmp_path: Path, capsys) -> None:
    """A write that fails after the work (a full disk) names the file, not only the OS's words."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet",
                                 "--estimator", "coulomb", "--no-bar", "--json", "/dev/full"])
    assert_one_line_error(code, err, "/dev/full: cannot write the JSON")


def test_a_blf_log_shorter_than_its_header_is_named_so(tmp_path: Path, capsys) -> None:
    whole = tmp_path / "whole.blf"
    _write_log(whole, [1.0 + 0.1 * k for k in range(30)])
    stub = tmp_path / "stub.blf"
    stub.write_bytes(whole.read_bytes()[:40])
    code, err = run_cli(capsys, ["replay", str(stub), "--no-send", "--fast", "--quiet"])
    assert_one_line_error(code, err, "stub.blf: cannot read as a blf CAN log at start: the file ends inside")


def test_a_dbc_cut_short_is_named_so(tmp_path: Path, capsys) -> None:
    """cantools answers a DBC that ends inside its header with 'list index out of range'; the
    message says what that means."""
    dbc = tmp_path / "cut.dbc"
    dbc.write_bytes(Path(DEFAULT_INPUT_DBC).read_bytes()[:300])
    code, err = run_cli(capsys, ["check", "--config", str(_config_file(tmp_path, dbc))])
    assert code == 2 and "Traceback" not in err, err
    assert "cut.dbc: the file ends inside a definition" in err, err


@pytest.mark.parametrize("body, field", [
    ("[ecm2rc_ekf]\nvoltage_noise_v = \"abc\"\n", "ecm2rc_ekf.voltage_noise_v"),
    ("[ecm2rc_ekf]\nvoltage_noise_v = 1e300\n", "ecm2rc_ekf.voltage_noise_v"),
    ("[ecm2rc_ekf]\nvoltage_noise_v = nan\n", "ecm2rc_ekf.voltage_noise_v"),
    ("[ecm2rc_ekf]\nsoc_clip = 0.5\n", "ecm2rc_ekf.soc_clip"),
    ("[ecm2rc_ekf]\nadaptive_noise_shape = \"bogus\"\n", "ecm2rc_ekf.adaptive_noise_shape"),
    ("[ecm2rc_ekf]\nsoc0_std = 0\n", "ecm2rc_ekf.soc0_std"),
    ("ecm2rc_ekf = 3\n", "'ecm2rc_ekf' must be a table"),
    ("voltage_noise_v = 0.5\n[estimator]\n", "voltage_noise_v beside the [estimator] table"),
])
def test_settings_the_filters_cannot_run_on_are_refused(tmp_path: Path, capsys, body: str, field: str) -> None:
    """The 2-RC EKF's tuning was checked by name only: a string, an overflow or a scalar for a range
    crashed inside the filter, and NaN or 0 ran to a row of nan or a filter that never corrects; a key
    beside an [estimator] table was dropped without a word."""
    settings = tmp_path / "s.toml"
    settings.write_text(body)
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet",
                                 "--estimator", "ecm2rc-ekf", "--settings", str(settings)])
    assert_one_line_error(code, err, field)


def test_fit_refuses_a_recording_given_twice(tmp_path: Path, capsys) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    copy = tmp_path / "copy.csv"
    shutil.copy(rec, copy)
    for second, said in ((rec, "the same file as"), (copy, "a copy of")):
        code, err = run_cli(capsys, ["fit", str(rec), str(second), "--capacity-ah", "2.9", "-o", str(tmp_path / "c.toml")])
        assert_one_line_error(code, err, said)
        assert not (tmp_path / "c.toml").exists()


def test_bench_and_demo_never_write_over_an_input_or_each_other(tmp_path: Path, capsys) -> None:
    cell = tmp_path / "cell.toml"
    shutil.copy(DEFAULT_CELL_PROFILE, cell)
    before = cell.read_bytes()
    code, err = run_cli(capsys, ["bench", "--cells", "2", "--steps", "20", "--reference-steps", "5",
                                 "--cell", str(cell), "--json", str(cell)])
    assert_one_line_error(code, err, "is one of the input files")
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["demo", "--recording", str(rec), "--cells", "2", "--json", str(rec)])
    assert_one_line_error(code, err, "is one of the input files")
    both = str(tmp_path / "same.png")
    code, err = run_cli(capsys, ["demo", "--recording", str(rec), "--cells", "2", "--json", both, "--plot", both])
    assert_one_line_error(code, err, "give each output a file of its own")
    assert cell.read_bytes() == before and rec.read_text().startswith(HEADER)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
def test_an_output_onto_a_pipe_or_an_empty_name_is_refused(tmp_path: Path, capsys) -> None:
    """--json onto a named pipe waited for ever after the run for a reader; -o '' wrote into the
    current folder."""
    fifo = tmp_path / "out.json"
    os.mkfifo(fifo)
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(DEFAULT_CELL_PROFILE), "--quiet",
                                 "--estimator", "coulomb", "--no-bar", "--json", str(fifo)])
    assert code == 2 and "is a pipe or socket" in err and "Traceback" not in err, err
    code, err = run_cli(capsys, ["schema", "-o", ""])
    assert code == 2 and "an empty name" in err and "Traceback" not in err, err


def test_a_capacity_many_times_too_large_is_warned_of() -> None:
    """The bundled drive with its own profile: the capacity it was characterised with passes, in whole
    and in a 10-minute window; a hundred times it, which passes every C-rate rule (its peak is still
    0.05C), is named with the factor the voltage reads."""
    from service.cell.profile import load_profile
    from service.cell.truth import capacity_slip
    from service.recording import load_recording

    profile = load_profile(DEFAULT_CELL_PROFILE)
    table, capacity = profile.ocv_table(), profile.effective_capacity_ah
    rec = load_recording(Path(__file__).resolve().parents[1] / "service" / "data" / "pan18650pf_25C_US06.csv")
    assert capacity_slip(rec, table, capacity, "--capacity-ah") is None
    window = rec.time_s < rec.time_s[0] + 600.0
    head = type(rec)(**{**rec.__dict__, **{k: v[window] for k, v in rec.__dict__.items()
                                          if isinstance(v, np.ndarray) and v.shape == rec.time_s.shape}})
    assert capacity_slip(head, table, capacity, "--capacity-ah") is None
    slip = capacity_slip(rec, table, 100 * capacity, "--capacity-ah")
    assert slip is not None and f"--capacity-ah {100 * capacity:g} Ah" in slip and "times too large" in slip, slip


def test_diagnose_warns_of_a_capacity_many_times_too_large_before_it_fits(tmp_path: Path, capsys) -> None:
    rec = Path(__file__).resolve().parents[1] / "service" / "data" / "pan18650pf_25C_US06.csv"
    text = DEFAULT_CELL_PROFILE.read_text()
    cell = tmp_path / "cell.toml"
    cell.write_text(text.replace("capacity_ah = 2.77", "capacity_ah = 277.0", 1))
    assert cell.read_text() != text
    # --save-effect without --save-profile is refused after the input checks, so nothing is fitted
    code, err = run_cli(capsys, ["diagnose", str(rec), "--cell", str(cell), "--save-effect", "none", "-q"])
    assert code == 2 and "warning" in err and "the profile's capacity_ah 277 Ah" in err, err
    assert "times too large" in err and "--save-effect needs --save-profile" in err, err


def test_evaluate_warns_of_a_profile_capacity_many_times_too_large(tmp_path: Path, capsys) -> None:
    rec = Path(__file__).resolve().parents[1] / "service" / "data" / "pan18650pf_25C_US06.csv"
    cell = tmp_path / "cell.toml"
    cell.write_text(DEFAULT_CELL_PROFILE.read_text().replace("capacity_ah = 2.77", "capacity_ah = 277.0", 1))
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(cell), "--estimator", "coulomb", "--no-bar", "-q"])
    assert code == 0 and "socd evaluate: warning:" in err and "times too large" in err, err


def test_an_output_onto_a_hard_link_of_an_input_is_refused(tmp_path: Path, capsys) -> None:
    cell = tmp_path / "cell.toml"
    shutil.copy(DEFAULT_CELL_PROFILE, cell)
    os.link(cell, tmp_path / "same.toml")
    code, err = run_cli(capsys, ["bench", "--cell", str(cell), "--json", str(tmp_path / "same.toml"),
                                 "--cells", "1", "--steps", "10", "--reference-steps", "2"])
    assert_one_line_error(code, err, "is one of the input files")
    assert cell.read_text() == DEFAULT_CELL_PROFILE.read_text()


def test_bench_counts_its_default_profile_as_an_input(tmp_path: Path, capsys, monkeypatch) -> None:
    """Without --cell, bench reads the bundled profile: --json onto it is refused (here a copy stands
    in for the bundled file, so a failure cannot destroy the checkout's)."""
    import service.config

    stand_in = tmp_path / "bundled.toml"
    shutil.copy(DEFAULT_CELL_PROFILE, stand_in)
    monkeypatch.setattr(service.config, "DEFAULT_CELL_PROFILE", stand_in)
    code, err = run_cli(capsys, ["bench", "--json", str(stand_in), "--cells", "1", "--steps", "10",
                                 "--reference-steps", "2"])
    assert_one_line_error(code, err, "is one of the input files")
    assert stand_in.read_text() == DEFAULT_CELL_PROFILE.read_text()


@pytest.mark.parametrize("target", ["config", "profile", "dbc"])
def test_replay_truth_out_never_replaces_a_file_its_config_names(tmp_path: Path, capsys, target: str) -> None:
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    dbc, cell = tmp_path / "in.dbc", tmp_path / "cell.toml"
    shutil.copy(DEFAULT_INPUT_DBC, dbc)
    shutil.copy(DEFAULT_CELL_PROFILE, cell)
    cfg = _config_file(tmp_path, dbc)
    cfg.write_text(cfg.read_text().replace(str(DEFAULT_CELL_PROFILE), str(cell)))
    victim = {"config": cfg, "profile": cell, "dbc": dbc}[target]
    before = victim.read_bytes()
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--config", str(cfg), "--truth-out", str(victim)))
    assert_one_line_error(code, err, "is one of the input files")
    assert victim.read_bytes() == before


@pytest.mark.parametrize("field", ["checkpoint", "dbc_input", "dbc_output", "profile", "zenoh", "the_config"])
def test_check_refuses_a_pipe_or_device_among_the_config_files(tmp_path: Path, capsys, field: str) -> None:
    """A named pipe blocked the reader forever; a device as the checkpoint (/dev/null) would have been
    replaced by a regular file at the first save."""
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    lines = {"checkpoint": '[checkpoint]\npath = "/dev/null"', "dbc_input": f'[dbc]\ninput = "{pipe}"',
             "dbc_output": f'[dbc]\noutput = "{pipe}"', "profile": f'cell_profile = "{pipe}"',
             "zenoh": f'[zenoh]\nconfig_file = "{pipe}"', "the_config": ""}
    cfg = tmp_path / "socd.toml"
    cfg.write_text(lines[field] + "\n")
    code, err = run_cli(capsys, ["check", "--config", str(pipe if field == "the_config" else cfg)])
    assert_one_line_error(code, err, "not a regular file")


@pytest.mark.parametrize("case", ["absolute_zero", "huge_ea", "entropic", "correction_lengths", "correction_volts",
                                  "surface_gain", "tiny_order", "tiny_c_df", "soc_resistance_no_temps"])
def test_a_profile_extension_beyond_plausible_is_refused(tmp_path: Path, capsys, case: str) -> None:
    """Extensions crashed the commands (a reference temperature at absolute zero divided by zero; lists
    of unequal length), overflowed (a CPE order of 0.001), wrote NaN into the JSON (a 1e12 J/mol
    activation energy, a C of 1e-300) or moved the OCV by volts; each is refused on load, naming it."""
    ext = {
        "absolute_zero": ("[extensions.arrhenius]\nref_temp_c = -273.15\n", "ref_temp_c"),
        "huge_ea": ("[extensions.arrhenius]\nea_r_ohm_j_mol = 1e12\n", "ea_r_ohm_j_mol"),
        "entropic": ("[extensions.arrhenius]\nentropic_v_per_k = 10.0\n", "entropic_v_per_k"),
        "correction_lengths": ("[extensions.ocv_correction]\nsoc = [0.0, 0.5, 1.0]\ndelta_v = [0.0, 0.01]\n",
                               "delta_v has 2 values"),
        "correction_volts": ("[extensions.ocv_correction]\nsoc = [0.0, 1.0]\ndelta_v = [50.0, 50.0]\n", "beyond"),
        "surface_gain": ("[extensions.diffusion_surface]\ntau_s = 100.0\ngain = 100.0\n", "gain"),
        "soc_resistance_no_temps": ("[extensions.soc_resistance]\nsoc = [0.0, 1.0]\ntemps_c = []\n"
                                    + "r_ohm_scale = []\nr_pol_scale = []\n", "temps_c"),
    }
    text = Path(DEFAULT_CELL_PROFILE).read_text()
    if case == "tiny_order":
        start = text.index("\nm = ") + 1  # the first point's order, however many digits the profile keeps
        text = text[:start] + "m = 0.001" + text[text.index("\n", start):]
        field = "parameters.0.m"
    elif case == "tiny_c_df":
        start = text.index("c_df = ")
        text = text[:start] + "c_df = 1e-300" + text[text.index("\n", start):]
        field = "time constant"
    else:
        block, field = ext[case]
        text = text.replace("[notes]", block + "\n[notes]", 1)
    path = tmp_path / f"{case}.toml"
    path.write_text(text)
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["evaluate", str(rec), "--cell", str(path), "--quiet"])
    assert_one_line_error(code, err, str(path))
    assert field in err, err


def test_json_output_writes_a_value_that_is_not_finite_as_null(tmp_path: Path, capsys) -> None:
    import json

    from service.commands.common_args import write_json

    out = tmp_path / "r.json"
    write_json(str(out), {"a": float("nan"), "b": [1.0, float("inf")], "c": np.float64(2.5)})
    assert json.loads(out.read_text()) == {"a": None, "b": [1.0, None], "c": 2.5}
    # the warning names where (a 10-minute recording's capacity signature had an infinite range, and
    # the warning blamed "a model that diverged" without saying which value)
    assert "2 value(s) in the JSON were not finite (NaN or infinity) and are written as null: a, b[1]" in \
        capsys.readouterr().err


@pytest.mark.parametrize("case", ["shared_frame_id", "input_scale_zero", "soc_too_narrow", "index_too_narrow"])
def test_check_and_run_refuse_a_dbc_that_would_decode_or_publish_wrong(tmp_path: Path, capsys, case: str) -> None:
    """Each passed `socd check` and then went wrong without a word: two messages on one frame ID (every
    voltage frame decoded as temperatures, no cell ever estimated), a mapped signal of scale 0 (replay
    crashed dividing by it), an output SOC signal of 4 bits (every cell published as 0.15 %), a cell
    index of 2 bits on an 8-cell pack (cells 4-7 never published)."""
    dbc_in, dbc_out = tmp_path / "in.dbc", tmp_path / "out.dbc"
    text_in, text_out = DEFAULT_INPUT_DBC.read_text(), DEFAULT_OUTPUT_DBC.read_text()
    edits = {
        "shared_frame_id": ("in", "BO_ 288 BMS_CellTemps:", "BO_ 272 BMS_CellTemps:", "share frame ID 0x110"),
        "input_scale_zero": ("in", "SG_ BMS_Cell001_V", None, "scale factor of 0"),
        "soc_too_narrow": ("out", "SG_ SOCD_Soc m0 : 8|16@1+ (0.01,0.0) [0|100]",
                           "SG_ SOCD_Soc m0 : 8|4@1+ (0.01,0.0) [0|0.15]", "SOCD_Soc carries 0 to 0.15"),
        "index_too_narrow": ("out", "SG_ SOCD_SocCellIndex M : 0|8@1+ (1,0) [0|255]",
                             "SG_ SOCD_SocCellIndex M : 0|2@1+ (1,0) [0|3]", "SOCD_SocCellIndex carries 0 to 3"),
    }
    which, old, new, expected = edits[case]
    if case == "input_scale_zero":  # the first cell voltage signal's factor set to 0
        line = next(ln for ln in text_in.splitlines() if old in ln)
        start = line.index("(")
        new, old = line[:start] + "(0," + line[line.index(",", start) + 1:], line
    assert old in (text_in if which == "in" else text_out), old
    dbc_in.write_text(text_in.replace(old, new, 1) if which == "in" else text_in)
    dbc_out.write_text(text_out.replace(old, new, 1) if which == "out" else text_out)
    cfg = tmp_path / "socd.toml"
    cfg.write_text(f'[dbc]\ninput = "{dbc_in}"\noutput = "{dbc_out}"\n[pack]\nn_cells = 8\n'
                   f'[checkpoint]\npath = "{tmp_path / "state.npz"}"\n')
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert code == 2 and expected in err and "Traceback" not in err, err
    code, err = run_cli(capsys, ["run", "--config", str(cfg)])
    assert_one_line_error(code, err, expected)


def test_fit_says_when_a_one_branch_ocv_table_is_read_as_the_mean(tmp_path: Path, capsys) -> None:
    from service.cell.ocv import ocv_table_branch

    table = tmp_path / "charge.csv"
    table.write_text("soc,ocv_charge_v\n0,3.0\n0.5,3.6\n1,4.1\n")
    assert ocv_table_branch(table) == "charge"
    mean = tmp_path / "mean.csv"
    mean.write_text("soc,ocv_v\n0,3.0\n0.5,3.6\n1,4.1\n")
    assert ocv_table_branch(mean) is None
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    # the recording is too short to fit; the notice comes first, even with -q
    _, err = run_cli(capsys, ["fit", str(rec), "--ocv", str(table), "--capacity-ah", "2.9", "-q",
                              "-o", str(tmp_path / "c.toml")])
    assert "its only OCV column is the charge branch (ocv_charge_v), read here as the mean OCV" in err, err


def test_replay_warns_when_a_mapping_scale_rounds_the_current_away(tmp_path: Path, capsys) -> None:
    """mapping.current_scale = 1000 sent 0 A in every current frame without a word (a scale that clips
    was already warned of)."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    cfg = _config_file(tmp_path, DEFAULT_INPUT_DBC, "[mapping]\ncurrent_scale = 1000.0\n")
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--config", str(cfg), "--cells", "8"))
    assert code == 0 and "sent as its offset" in err and "BMS_PackCurrent 30 of 30" in err, err
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--cells", "8"))
    assert code == 0 and "sent as its offset" not in err, err


def test_a_start_soc_the_drive_runs_past_is_named(tmp_path: Path, capsys) -> None:
    """--soc0 0 on a discharge: replay sent a negative truth SOC and voltages beyond the OCV table without a
    word (now a warning naming the cell and when), and the demo stopped after 1 s of the drive (refused)."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--cells", "8", "--soc0", "0"))
    assert code == 0 and "true SOC leaves [0, 1]" in err, err
    code, err = run_cli(capsys, _replay_argv(rec, tmp_path, "--cells", "8", "--soc0", "0.5"))
    assert code == 0 and "true SOC leaves" not in err, err
    code, err = run_cli(capsys, ["demo", "--recording", str(rec), "--soc0", "0", "--cells", "2"])
    assert_one_line_error(code, err, "leaves the pack no room for it")


@pytest.mark.parametrize("case", ["replay_speed", "demo_speed", "schema_dash", "replay_pipe", "demo_pipe", "empty_cell"])
def test_flags_named_plainly(tmp_path: Path, capsys, case: str) -> None:
    """A speed-up of 1e-12 ended in "timestamp out of range for platform time_t" (1e-9 ran for ever), `schema -o -`
    made a folder named '-', a pipe given as a recording was "no such file", and an empty --cell read as '.'."""
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    argv, expected = {
        "replay_speed": (_replay_argv(rec, tmp_path, "--speed", "1e-12"), "argument --speed"),
        "demo_speed": (["demo", "--speed", "1e-9"], "argument --speed"),
        "schema_dash": (["schema", "-o", "-"], "'-' is no folder"),
        "replay_pipe": (_replay_argv(pipe, tmp_path), "not a regular file"),
        "demo_pipe": (["demo", "--recording", str(pipe)], "not a regular file"),
        "empty_cell": (["evaluate", str(rec), "--cell", ""], "an empty name"),
    }[case]
    code, err = run_cli(capsys, argv)
    assert code == 2 and expected in err and "Traceback" not in err, err
    assert not (Path.cwd() / "-").exists()


def test_an_environment_override_that_is_no_json_list_is_named(capsys, monkeypatch) -> None:
    monkeypatch.setenv("SOCD_ZENOH__LISTEN", "tcp/127.0.0.1:7447")
    code, err = run_cli(capsys, ["check"])
    assert_one_line_error(code, err, "SOCD_ZENOH__LISTEN")
    assert "JSON" in err, err


@pytest.mark.parametrize("endpoint, expected", [("foo/bar", "no link protocol 'foo'"),
                                                ("tcp/:7447", "needs a host before the port")])
def test_check_refuses_a_zenoh_endpoint_the_session_cannot_open(tmp_path: Path, capsys, endpoint: str,
                                                                  expected: str) -> None:
    """Both passed check; run then retried for ever ("Unicast not supported for foo protocol") or went
    down at once with no reason given."""
    cfg = tmp_path / "socd.toml"
    cfg.write_text(f'[zenoh]\nconnect = ["{endpoint}"]\n')
    code, err = run_cli(capsys, ["check", "--config", str(cfg)])
    assert_one_line_error(code, err, expected)


@pytest.mark.parametrize("argv", [["replay", "--no-send"], ["demo", "--recording"]])
def test_a_misspelt_recording_name_names_the_one_socd_ships(tmp_path: Path, capsys, monkeypatch, argv: list[str]) -> None:
    """`socd replay pan18650pf_25C_US6` said only "no such file" and `socd demo --recording` the same
    typo "no such recording", where evaluate, fit and diagnose name the recording socd ships."""
    monkeypatch.chdir(tmp_path)
    code, err = run_cli(capsys, [*argv, "pan18650pf_25C_US6"])
    assert_one_line_error(code, err, "pan18650pf_25C_US6: no such ")
    assert "(socd ships the recording pan18650pf_25C_US06: give its name alone)" in err


def test_replay_of_a_missing_cell_profile_does_not_ask_for_the_flag_given(tmp_path: Path, capsys) -> None:
    """`socd replay ... --cell nope` ended its one line with "(give --cell or set cell_profile in the
    config)": the user had given --cell, and the line already lists the bundled profiles."""
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    code, err = run_cli(capsys, ["replay", str(rec), "--no-send", "--cell", "nope"])
    assert_one_line_error(code, err, "nope: cannot read cell profile: no such file (bundled profiles, by name: ")
    assert "give --cell" not in err


@pytest.mark.parametrize("command", ["check", "run"])
@pytest.mark.parametrize("body, names", [
    ('[bus]\nchanel = "can0"\n', "c.toml: bus.chanel: unknown key (did you mean channel?)"),
    ("[estimator]\nmemory_lenght = 8\n", "c.toml: estimator.memory_lenght: unknown key (did you mean memory_length?)"),
    ('[mapping]\ncells = [{cell = 0, signal = "BMS_Cell001_V", sign = 1}]\n',
     "c.toml: mapping.cells[0].sign: unknown key (did you mean signal?)"),
    ("colour = 1\n", "c.toml: colour: unknown key (socd schema lists the keys)"),
])
def test_an_unknown_config_key_is_called_so_with_the_key_meant(tmp_path: Path, capsys, command: str, body: str,
                                                                names: str) -> None:
    """A misspelt key in a config was refused as pydantic words it, "bus.chanel: Extra inputs are not
    permitted", which names neither what is wrong with it nor the key the user meant."""
    code, err = run_cli(capsys, [command, "--config", str(_config_with(tmp_path, body))])
    assert_one_line_error(code, err, names)


@pytest.mark.parametrize("argv, names", [
    (["fit", "r.csv", "--capacity-ah", "-1", "-o", "c.toml"], "socd fit: error: argument --capacity-ah: must be > 0, got -1"),
    (["diagnose", "r.csv", "--ocv", "o.csv", "--capacity-ah", "x"],
     "socd diagnose: error: argument --capacity-ah: expected a number, got 'x'"),
    (["evaluate", "r.csv"], "socd evaluate: error: the following arguments are required: --cell"),
    (["demoo"], "socd: error: argument COMMAND: invalid choice: 'demoo'"),
    # an option the command does not have is named by the command (it read "socd: error: ...")
    (["run", "--bogus"], "socd run: error: unrecognized arguments: --bogus"),
    (["--bogus"], "socd: error: unrecognized arguments: --bogus"),
])
def test_a_usage_error_is_one_line(tmp_path: Path, capsys, monkeypatch, argv: list[str], names: str) -> None:
    """A wrong --capacity-ah printed socd fit's 17-line usage block before the one line that said what
    was wrong, where every other bad input gets that line alone."""
    monkeypatch.chdir(tmp_path)
    code, err = run_cli(capsys, argv)
    assert_one_line_error(code, err, names)


def test_diagnose_refuses_an_ocv_table_the_recording_rests_above(tmp_path: Path, capsys) -> None:
    """The bundled 4.2 V drive with an LFP-like table that ends at 3.65 V: every rest read as SOC 1
    (clipped), and `socd diagnose` left 207 mV held out and exited 0 (on a synthetic drive it named
    capacity)."""
    rec = Path(__file__).resolve().parents[1] / "service" / "data" / "pan18650pf_25C_US06.csv"
    ocv = tmp_path / "lfp_ocv.csv"
    soc = np.linspace(0, 1, 21)
    ocv.write_text("soc,ocv_v\n" + "\n".join(f"{s:g},{2.5 + 1.15 * s ** 0.3:.4f}" for s in soc) + "\n")
    code, err = run_cli(capsys, ["diagnose", str(rec), "--ocv", str(ocv), "--capacity-ah", "2.77",
                                 "--effects", "capacity", "-q"])
    assert_one_line_error(code, err, f"{rec}: its voltage at rest or light load reaches ")
    assert f"above the OCV at full charge (3650 mV) of the OCV table {ocv}" in err, err


def test_no_shared_recording_rests_above_its_own_ocv_table() -> None:
    """The OCV-range check passes the bundled drive with its profile, and every shared recording with
    its own table (synthetic) or its cell's bundled profile (real)."""
    from service.cell.ocv import OcvTable, load_ocv_csv
    from service.cell.profile import load_profile
    from service.cell.truth import ocv_range_problem
    from service.commands.common_args import cell_file
    from service.recording import load_recording

    bundled = Path(__file__).resolve().parents[1] / "service" / "data" / "pan18650pf_25C_US06.csv"
    assert ocv_range_problem(load_recording(bundled), load_profile(DEFAULT_CELL_PROFILE).ocv_table(), "p") is None
    shared = Path(__file__).resolve().parents[2] / "shared" / "data"
    files = [p for p in sorted(shared.glob("real/*/*.csv")) + sorted(shared.glob("synthetic/*.csv"))
             if "soc_table" not in p.name and not p.stem.endswith("_ocv") and p.parent.name != "ocv"]
    if not files:
        pytest.skip("../shared/data is not here")
    cells = {"pan18650pf": "panasonic_18650pf", "calce20r": "calce_inr18650_20r", "calce_a123": "calce_a123"}
    tables = {name: load_profile(cell_file(name)).ocv_table() for name in cells.values()}
    for path in files:
        if path.parent.name == "synthetic":
            table = OcvTable.from_points(*load_ocv_csv(path.with_name(path.stem + "_ocv.csv")))
        else:
            table = tables[next(c for prefix, c in cells.items() if path.name.startswith(prefix))]
        assert ocv_range_problem(load_recording(path), table, "t") is None, path.name


def test_diagnose_says_when_a_recording_opens_under_load(tmp_path: Path, capsys) -> None:
    """A drive cut in its middle: its initial SOC is read from the first voltage corrected by R_ohm·I,
    4 % of SOC low on a synthetic DST, and diagnose named hysteresis with exit 0 and no word of it (its
    JSON said the SOC came from an opening rest). It now says so, once, before it fits; --soc0 silences it."""
    from service.assets import bundled_recording
    from service.diagnosis.pipeline import initial_state_text
    from service.recording import load_recording, save_recording

    rec = load_recording(bundled_recording())
    k = int(np.argmax((rec.time_s > 1000.0) & (rec.current_a > 2.0)))
    cut = save_recording(tmp_path / "mid_drive.csv", np.column_stack(
        [rec.time_s[k:], rec.current_a[k:], rec.voltage_v[k:], rec.temperature_c[k:]]))
    # --save-effect without --save-profile is refused after the input checks, so nothing is fitted
    argv = ["diagnose", str(cut), "--cell", str(DEFAULT_CELL_PROFILE), "--save-effect", "none", "-q"]
    code, err = run_cli(capsys, argv)
    lines = err.splitlines()
    assert code == 2 and len(lines) == 2 and "--save-effect needs --save-profile" in lines[1], err
    assert f"warning: {cut}: it opens under load ({load_recording(cut).current_a[0]:g} A)" in lines[0], err
    assert "give --soc0 if it is known" in lines[0], err
    code, err = run_cli(capsys, [*argv, "--soc0", "0.9"])
    assert code == 2 and "warning" not in err, err
    code, err = run_cli(capsys, ["diagnose", str(bundled_recording()), "--cell", str(DEFAULT_CELL_PROFILE),
                                 "--save-effect", "none", "-q"])
    assert code == 2 and "warning" not in err, err  # the whole drive opens at rest
    assert "opens under load" in initial_state_text(load_recording(cut), 2.77, None)
    assert "opening rest" in initial_state_text(rec, 2.77, None)
    assert "--soc0" in initial_state_text(load_recording(cut), 2.77, 0.9)


@pytest.mark.parametrize("sep, named", [(";", "';'"), ("\t", "tabs")])
@pytest.mark.parametrize("which", ["recording", "ocv"])
def test_a_file_separated_by_semicolons_or_tabs_is_named_so(tmp_path: Path, capsys, sep: str, named: str,
                                                            which: str) -> None:
    """A spreadsheet's export in a decimal-comma locale: its header reads as one field, and the error said
    the columns time_s, current_a, ... were missing from a header that shows every one of them."""
    ocv = tmp_path / "ocv.csv"
    ocv.write_text("soc,ocv_v\n" + "\n".join(f"{s:g},{3.0 + 1.2 * s:g}" for s in np.linspace(0, 1, 11)) + "\n")
    rec = _recording(tmp_path, "ok.csv", GOOD_ROWS)
    bad = rec if which == "recording" else ocv
    bad.write_text(bad.read_text().replace(",", sep))
    code, err = run_cli(capsys, ["diagnose", str(rec), "--ocv", str(ocv), "--capacity-ah", "2.9", "-q"])
    assert_one_line_error(code, err, f"{bad}: row 1: the fields are separated by {named}, not commas")
