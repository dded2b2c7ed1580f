"""``research.pulse_fit_check``: a profile against the pulse test it was fitted on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_fitting import TRUE, profile

from research.pulse_fit_check import SOC_BANDS, check_recording, main, pulse_summary, read_json
from service.cell.trajectory import simulate
from service.recording import save_recording

pytestmark = pytest.mark.research


def hppc_like(path: Path, capacity_ah: float = 2.0) -> Path:
    """A pulse test through ``profile()``'s own model: at each SOC level a 1C and a 4C discharge
    pulse of 10 s, each after a rest of 400 s, then 10 % of the capacity at 1C; from full to 0.1."""
    current: list[float] = [0.0] * 600
    for _ in range(8):
        for c_rate in (1.0, 4.0):
            current += [c_rate * capacity_ah] * 10 + [0.0] * 400
        current += [capacity_ah] * 360 + [0.0] * 400
    i = np.array(current)
    t = np.arange(i.size, dtype=float)
    temp = np.full(i.size, 25.0)
    v, _ = simulate(profile(), t, i, temp, 1.0)
    return save_recording(path, np.column_stack([t, i, v, temp]), fmt="%.6f")


def test_the_profiles_own_pulse_test_reads_no_residual_and_equal_resistances(tmp_path: Path) -> None:
    check = check_recording(profile(), str(hppc_like(tmp_path / "hppc.csv")), 2.0)
    assert set(check.load_residual_mv) == {name for _, name in SOC_BANDS}
    assert all(abs(r) < 0.5 for r in check.load_residual_mv.values())
    rows = pulse_summary(check)
    assert {(c, after) for c, after, *_ in rows} == {(1.0, 1.0), (1.0, 10.0), (4.0, 1.0), (4.0, 10.0)}
    for c_rate, _, measured, model, n in rows:
        assert n == (16 if c_rate == 1.0 else 8)  # at 1C the pulses and the SOC steps' starts
        assert model == pytest.approx(measured, abs=0.2)


def test_a_profile_with_more_ohmic_resistance_reads_it_in_every_pulse(tmp_path: Path) -> None:
    """10 mΩ more R_ohm: every pulse reads 10 mΩ more in the model, and the residual under load is
    negative (a model that polarises too much)."""
    rec = hppc_like(tmp_path / "hppc.csv")
    more = profile(TRUE.model_copy(update={"r_ohm": TRUE.r_ohm + 0.010}))
    check = check_recording(more, str(rec), 2.0)
    for _, _, measured, model, _ in pulse_summary(check):
        assert model - measured == pytest.approx(10.0, abs=0.3)
    assert all(r < -5.0 for r in check.load_residual_mv.values())


def test_the_command_writes_json_the_table_reads_back_and_names_a_bad_capacity(tmp_path: Path, capsys) -> None:
    from service.cell.profile import save_profile

    rec = hppc_like(tmp_path / "hppc.csv")
    cell = tmp_path / "cell.toml"
    save_profile(profile(), cell)
    out = tmp_path / "check.json"
    assert main([str(cell), str(rec), "--capacity-ah", "2.0", "--json", str(out)]) == 0
    assert "1C measured / model" in capsys.readouterr().out
    assert read_json(str(out))[0].recording == "hppc.csv"
    assert main([str(cell), str(rec), "--capacity-ah", "-1"]) == 2
    assert "--capacity-ah -1" in capsys.readouterr().err
    assert main([str(cell), str(tmp_path / "missing.csv"), "--capacity-ah", "2.0"]) == 2
    assert "missing.csv" in capsys.readouterr().err
