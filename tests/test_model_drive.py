"""``research.model_drive``: a recording's current and temperature through a profile's own model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from research.model_drive import main as model_drive
from service.cell.trajectory import simulate
from service.recording import load_recording

pytestmark = pytest.mark.research


def test_the_written_recording_is_the_profiles_model_with_its_truth(tmp_path: Path, nmc_recording, nmc_profile,
                                                                     nmc_profile_file) -> None:
    rec = nmc_recording(name="drive", duration_s=900, seed=3, soc0=0.9)
    out = tmp_path / "model.csv"
    assert model_drive([str(rec.path), "-o", str(out), "--cell", str(nmc_profile_file), "--soc0", "0.9",
                        "--noise-v", "0"]) == 0
    got = load_recording(out)
    v, soc = simulate(nmc_profile, rec.time_s, rec.current_a, rec.temperature_c, 0.9)
    np.testing.assert_allclose(got.current_a, rec.current_a, atol=1e-6)
    np.testing.assert_allclose(got.voltage_v, v, atol=1e-6)
    np.testing.assert_allclose(got.soc_true, soc, atol=1e-6)
    assert model_drive([str(rec.path), "-o", str(out), "--soc0", "1.5"]) == 2
