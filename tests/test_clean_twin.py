"""The clean twin of a labelled synthetic recording (research.clean_twin).

The arithmetic and the label handling run everywhere; the twin itself needs PyBaMM and the
labelled data (``../shared/data/synthetic``), and is skipped where either is missing.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from research.clean_twin import (
    DEFAULT_DATA,
    TwinError,
    excess_removed,
    faithful,
    load_label,
    main,
    noise_free_rms_mv,
    simulate_twin,
    twin_current,
)
from service.recording import load_recording

pytestmark = pytest.mark.research


def test_excess_removed_is_the_share_of_the_part_above_the_floor():
    assert excess_removed(20.0, 15.0, 10.0) == pytest.approx(0.5)
    assert excess_removed(20.0, 10.0, 10.0) == pytest.approx(1.0)
    assert excess_removed(20.0, 22.0, 10.0) == pytest.approx(-0.2)
    assert excess_removed(10.0, 9.0, 10.0) is None, "nothing above the floor: no share to give"
    assert excess_removed(9.0, 9.0, 10.0) is None


def test_noise_free_rms_takes_the_voltage_noise_out():
    rng = np.random.default_rng(1)
    noise = rng.normal(0.0, 1.5e-3, 200_000)
    assert noise_free_rms_mv(noise, 1.5) < 0.1
    assert noise_free_rms_mv(noise + 0.010, 1.5) == pytest.approx(10.0, abs=0.05)


def test_faithful_allows_a_millivolt_and_five_percent():
    assert faithful(10.79, 10.7) and faithful(0.9, 0.0) and faithful(102.0, 98.0)
    assert not faithful(1.2, 0.0) and not faithful(104.0, 98.0)


def test_twin_current_takes_the_sensor_offset_out():
    i = np.array([0.0, 1.0, -2.0])
    assert np.allclose(twin_current(i, {"current_offset_a": -0.02}), [0.02, 1.02, -1.98])
    assert np.allclose(twin_current(i, {"current_offset_a": 0.0}), i)


def _labels(tmp_path, entry):
    (tmp_path / "labels.json").write_text(json.dumps({"rec_a": entry}))
    return tmp_path


def test_label_errors_name_the_file_and_the_stem(tmp_path):
    with pytest.raises(TwinError, match="no labels file"):
        load_label(tmp_path, "rec_a")
    data = _labels(tmp_path, {"model": "SPMe", "cell": "okane2022"})
    with pytest.raises(TwinError, match="no label for 'rec_b'"):
        load_label(data, "rec_b")
    with pytest.raises(TwinError, match=r"labels.json: label 'rec_a' lacks soc0, current_offset_a, noise"):
        load_label(data, "rec_a")


def test_cli_rejects_an_unknown_stem_and_a_folder_without_labels(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--data", str(tmp_path)])
    assert exc.value.code == 2 and "no labels file" in capsys.readouterr().err
    data = _labels(tmp_path, {"model": "SPMe"})
    with pytest.raises(SystemExit) as exc:
        main(["--data", str(data), "--stems", "rec_a,nope"])
    assert exc.value.code == 2 and "no label for nope" in capsys.readouterr().err


@pytest.mark.parametrize("stem, label_mv", [("dst_s101_4e4041", 0.0), ("hppc_s102_131537", 10.7)])
def test_twin_is_the_generators_no_effect_run(stem, label_mv):
    """The clean file's twin reproduces it to within the voltage noise, and the hysteresis file's
    twin differs from it by the label's 10.7 mV: the twins are the labelled no-effect runs."""
    pytest.importorskip("pybamm")
    if not (DEFAULT_DATA / f"{stem}.csv").is_file():
        pytest.skip(f"labelled data not found at {DEFAULT_DATA}")
    label = load_label(DEFAULT_DATA, stem)
    rec = load_recording(DEFAULT_DATA / f"{stem}.csv")
    v, temp = simulate_twin(rec.time_s, twin_current(rec.current_a, label), label)
    assert v.size == len(rec)
    diff_mv = noise_free_rms_mv(rec.voltage_v - v, label["noise"]["v_sigma_mv"])
    assert diff_mv == pytest.approx(label["voltage_diff_vs_no_effect_mv"]["rms_mv"], abs=0.5)
    assert faithful(diff_mv, label_mv)
    if label_mv == 0.0:
        assert np.sqrt(np.mean((rec.temperature_c - temp) ** 2)) < 0.15, "the same heating, to the sensor noise"


def test_show_prints_an_earlier_runs_table_with_the_best_cut(tmp_path, capsys):
    from research.clean_twin import TwinRow

    row = TwinRow(stem="rec_a", effect="hysteresis", model="SPMe", twin_diff_mv=10.68, label_diff_mv=10.7,
                  twin_faithful=True, twin_verdict="none", twin_state="unexplained", verdict="hysteresis",
                  split="chronological", floor_mv=10.0, before_mv=12.5, after_mv=11.0, seconds=1.0)
    assert row.best_cut == pytest.approx(0.2) and row.excess_removed == pytest.approx(0.6)
    path = tmp_path / "twins.json"
    path.write_text(json.dumps([row.to_json()]))
    assert main(["--show", str(path)]) == 0
    out = capsys.readouterr().out
    assert "| rec_a | hysteresis | 10.68 (10.70) | none | hysteresis |" in out and "| +12.0 % | 20.0 % | 60 % |" in out
    path.write_text("[{}]")
    with pytest.raises(SystemExit) as exc:
        main(["--show", str(path)])
    assert exc.value.code == 2 and "not a clean_twin --json file" in capsys.readouterr().err
