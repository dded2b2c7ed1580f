"""``socd fit`` block-averages recordings sampled faster than its period (1 s by default), so the
G-L memory it fits with spans 16 s whatever the logging rate (service/characterisation/block_average.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.cell.profile import load_profile
from service.characterisation.block_average import block_average, describe, to_fit_period
from service.cli import main
from service.recording import Recording, load_recording

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "service" / "data" / "pan18650pf_25C_US06.csv"
SHARED = ROOT.parent / "shared" / "data" / "real" / "panasonic_18650pf"


def _at_10hz(rec: Recording) -> Recording:
    """``rec`` (evenly sampled, period P a whole number of seconds) logged at 10 Hz with jittered stamps:
    each value held over the interval that starts at its own stamp, as a logger of a signal held there
    would see it.  Averaged to 1 s it is ``rec`` again, each value repeated P times."""
    period = float(np.median(np.diff(rec.time_s)))
    per = round(period / 0.1)
    rng = np.random.default_rng(3)
    t = (rec.time_s[:, None] + 0.1 * np.arange(per)[None, :]).ravel()
    t = t + rng.uniform(0.0, 0.004, t.size)  # never across a block edge
    t[0] = rec.time_s[0]

    def held(x: np.ndarray) -> np.ndarray:
        return np.repeat(x, per)

    return Recording(rec.path, t, held(rec.current_a), held(rec.voltage_v), held(rec.temperature_c))


def test_a_1s_recording_logged_at_10hz_averages_back_to_itself() -> None:
    rec = load_recording(BUNDLED).slice(0, 900)
    back = block_average(_at_10hz(rec), 1.0)
    np.testing.assert_array_equal(back.time_s, rec.time_s)
    for col in ("current_a", "voltage_v", "temperature_c"):
        np.testing.assert_allclose(getattr(back, col), getattr(rec, col), rtol=0, atol=1e-12)


def test_a_gap_stays_a_gap_and_soc_true_is_averaged() -> None:
    t = np.r_[np.arange(0.0, 3.0, 0.5), np.arange(10.0, 12.0, 0.5)]
    x = np.arange(t.size, dtype=float)
    rec = Recording(Path("gap.csv"), t, x, x, x, soc_true=x / 10)
    out = block_average(rec, 1.0)
    np.testing.assert_array_equal(out.time_s, [0.0, 1.0, 2.0, 10.0, 11.0])
    np.testing.assert_array_equal(out.current_a, [0.5, 2.5, 4.5, 6.5, 8.5])
    assert out.soc_true is not None
    np.testing.assert_allclose(out.soc_true, out.current_a / 10)


def test_only_recordings_faster_than_the_period_are_averaged() -> None:
    slow = load_recording(BUNDLED).slice(0, 300)
    fast = _at_10hz(slow)
    done = to_fit_period([slow, fast], 1.0)
    assert [a.averaged for a in done] == [False, True]
    assert done[0].recording is slow
    assert done[1].period_s == pytest.approx(0.1, abs=0.01)
    line = describe(done, 1.0)
    assert line is not None and "pan18650pf_25C_US06 (0.1 s)" in line and "--fit-period 0" in line
    assert [a.averaged for a in to_fit_period([fast], 0.0)] == [False]
    assert describe(to_fit_period([slow], 1.0), 1.0) is None
    assert main(["fit", str(BUNDLED), "--capacity-ah", "2.77", "--fit-period", "60", "-o", "unused.toml"]) == 2
    with pytest.raises(ValueError, match="block period"):
        block_average(slow, 0.0)


@pytest.mark.skipif(not (SHARED / "fullrate_10Hz").is_dir(), reason="the shared Panasonic data is not on this machine")
def test_the_panasonic_10hz_log_averages_to_the_shared_1s_file() -> None:
    """The shared 1 s files are block averages of the 10 Hz logs, stamped at the block's start;
    samples stamped right on a block edge may fall either side, so a few blocks differ."""
    fast = load_recording(SHARED / "fullrate_10Hz" / "pan18650pf_25C_US06_10Hz.csv")
    shared = load_recording(SHARED / "pan18650pf_25C_US06.csv")
    ours = block_average(fast, 1.0)
    assert len(ours) == len(shared)
    np.testing.assert_array_equal(ours.time_s, shared.time_s)
    same = np.abs(ours.current_a - shared.current_a) < 1e-4
    assert same.mean() > 0.97


def test_fit_on_10hz_data_keeps_the_16s_memory_unless_told(tmp_path: Path, nmc_recording, capsys) -> None:
    rec = nmc_recording(name="fast", duration_s=900, seed=4, soc0=0.95, dt_s=0.1)
    spans = {}
    for label, flags in (("default", []), ("recorded rate", ["--fit-period", "0"])):
        out = tmp_path / f"{label.replace(' ', '_')}.toml"
        rc = main(["fit", "--candidates", "1", str(rec.path), "--capacity-ah", "2.0", "--max-seconds", "1", "--force", "-o", str(out), *flags])
        err = capsys.readouterr().err
        assert rc == 0, err
        assert ("block-averaged to 1 s" in err) == (label == "default"), err
        spans[label] = load_profile(out).memory_span_s
    assert spans["default"] == pytest.approx(16.0)
    assert spans["recorded rate"] == pytest.approx(1.6, rel=0.05)


def test_diagnose_reads_a_10hz_log_as_its_1s_averages(tmp_path: Path, capsys) -> None:
    """research.validate's clear capacity case (4 s samples) logged at 10 Hz: diagnose averages it to
    1 s blocks, the rate its rules were chosen at, says so, and names the effect."""
    from research.validate import CAP, ocv_spec, write_case
    from tests.conftest import write_recording_csv

    slow = load_recording(write_case(tmp_path / "capacity_4s.csv", "capacity", "clear", seed=0))
    fast = _at_10hz(slow)
    path = write_recording_csv(tmp_path / "capacity_10hz.csv", fast.time_s, fast.current_a, fast.voltage_v,
                               fast.temperature_c)
    ocv = tmp_path / "ocv.csv"
    spec = ocv_spec()
    np.savetxt(ocv, np.column_stack([spec.soc, spec.ocv_v[0]]), delimiter=",", header="soc,ocv_v", comments="")
    out = tmp_path / "d.json"
    rc = main(["diagnose", str(path), "--ocv", str(ocv), "--capacity-ah", str(CAP), "--json", str(out),
               "--effects", "capacity,current_bias"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "capacity_10hz (0.1 s) block-averaged to 1 s" in err
    assert json.loads(out.read_text())["verdict"] == "capacity"
