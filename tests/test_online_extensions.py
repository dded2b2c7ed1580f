"""Diagnose's extensions in the online pipeline (issue 4, item 6: the extended profile is
used by ``socd evaluate`` and by the service).

The solid-diffusion surface lag and the temperature extension's entropic OCV slope are
the two terms the pipeline reads beyond the base model; each cell here is simulated by
the model itself (:func:`research.validate.simulate_cell`), so the truth is
exact, and scored with the term and with it dropped.  The last test runs the whole loop
(diagnose → saved profile → ``socd evaluate`` on a recording diagnose never saw).

The scoring drive (``research.roundtrip.score_drive``, 1704 samples at 4 s) is cut to its
first :data:`SCORE_SAMPLES` (40 min) here and to its first 850 (57 min) in the round trip: the
filters' cost grows with its length, and each term's SOC error shows well within that.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from research import roundtrip
from research.roundtrip import run_effect, score_drive
from research.validate import base_profile, simulate_cell
from service.cell.model import MtsFom, drive
from service.cell.profile import ArrheniusSpec, CellProfile, Extensions, SurfaceDiffusionSpec
from service.estimators.pipeline import PackEstimator, foukf
from service.estimators.settings import EstimatorSettings
from service.recording import Recording

SURFACE = SurfaceDiffusionSpec(tau_s=600.0, gain=0.08)
ENTROPIC = ArrheniusSpec(ref_temp_c=25.0, entropic_v_per_k=1.0e-3)  # 30 mV over the 5 → 35 °C ramp
#: the samples of ``score_drive(1)`` the filters are scored on here (the temperature ramp spans them)
SCORE_SAMPLES = 600


def _with(ext: Extensions) -> CellProfile:
    return base_profile().model_copy(update={"extensions": ext})


def _recording(case: dict) -> Recording:
    columns, soc = simulate_cell(case, score_drive(1)[:SCORE_SAMPLES], 1)
    t, i, v, temp = columns.T
    return Recording(Path("sim.csv"), t, i, v, temp, soc)


def _soc_rmse_pct(profile: CellProfile, rec: Recording) -> float:
    trace = foukf().run(rec, profile, 0.75)
    after = rec.time_s >= 600.0
    return float(100.0 * np.sqrt(np.mean((trace.soc - rec.soc_true)[after] ** 2)))


def test_surface_lag_is_read_online():
    ext = Extensions(diffusion_surface=SURFACE)
    rec = _recording({"extensions": ext})
    with_term = _soc_rmse_pct(_with(ext), rec)
    without = _soc_rmse_pct(base_profile(), rec)
    assert with_term < 0.3, with_term
    assert without > 3 * with_term and without > 1.0, (with_term, without)


def test_entropic_ocv_slope_is_read_online():
    ext = Extensions(arrhenius=ENTROPIC)
    rec = _recording({"extensions": ext, "temp": "ramp"})
    with_term = _soc_rmse_pct(_with(ext), rec)
    without = _soc_rmse_pct(base_profile(), rec)
    assert with_term < 0.3, with_term
    assert without > 3 * with_term and without > 1.0, (with_term, without)


def test_a_zero_surface_gain_changes_nothing():
    rec = _recording({})
    plain = foukf().run(rec, base_profile(), 0.75)
    zero = foukf().run(rec, _with(Extensions(diffusion_surface=SurfaceDiffusionSpec(tau_s=600.0, gain=0.0))), 0.75)
    np.testing.assert_array_equal(plain.soc, zero.soc)
    np.testing.assert_array_equal(plain.v_pred, zero.v_pred)


def test_surface_deficit_follows_the_model_warm_and_survives_a_checkpoint():
    prof = _with(Extensions(diffusion_surface=SURFACE))
    rec = _recording({"extensions": Extensions(diffusion_surface=SURFACE)}).slice(0, 400)
    est = PackEstimator(prof, 2, EstimatorSettings(capacity_estimation="off"))  # the model counts with the profile capacity
    est.start(np.array([0.6, 0.7]))
    est.warm_start(rec)
    model = MtsFom(prof, prof.parameters_at(np.full(2, 25.0)), np.full(2, 0.7), est.settings.memory_length)
    drive(model, rec.time_s, rec.current_a, rec.temperature_c)
    assert np.all(est.surface_deficit > 0.01)
    np.testing.assert_allclose(est.surface_deficit, model.x_surf, rtol=1e-9)

    # online, the deficit is the same first-order lag of the current
    for k in range(1, 50):
        est.step(4.0, rec.current_a[k], rec.voltage_v[k:k + 1].repeat(2), np.full(2, 25.0))
        model.step(4.0, np.full(2, rec.current_a[k]), np.full(2, 25.0))
    np.testing.assert_allclose(est.surface_deficit, model.x_surf, rtol=1e-9)

    state = est.get_state()
    restored = PackEstimator(prof, 2, EstimatorSettings(capacity_estimation="off"))
    restored.set_state(state)
    np.testing.assert_array_equal(restored.surface_deficit, est.surface_deficit)
    # a checkpoint written before the deficit was kept loads as a relaxed surface
    del state["surface_deficit"]
    older = PackEstimator(prof, 2, EstimatorSettings(capacity_estimation="off"))
    older.set_state(state)
    np.testing.assert_array_equal(older.surface_deficit, np.zeros(2))
    # a restart relaxes it with the branches
    est.start(np.array([0.5, 0.5]))
    np.testing.assert_array_equal(est.surface_deficit, np.zeros(2))


@pytest.mark.slow
@pytest.mark.research
def test_diagnosed_diffusion_profile_improves_socd_evaluate_on_an_unseen_recording(tmp_path, monkeypatch):
    # both profiles are scored on the first 850 samples (57 min) of the unseen drive, not all 1704
    monkeypatch.setattr(roundtrip, "score_drive", lambda seed: score_drive(seed)[:850])
    row = run_effect("diffusion", "clear", tmp_path)
    assert row.verdict == "diffusion"
    for name in ("foukf", "fomiukf"):
        assert row.soc_rmse_extended_pct[name] < 0.5 * row.soc_rmse_base_pct[name], row
        assert row.v_rmse_extended_mv[name] < row.v_rmse_base_mv[name], row
    assert (tmp_path / "diffusion_clear_extended.toml").exists()
