"""The filters' defaults do not depend on the cell's size.

``k`` cells in parallel are one cell with ``k`` times the capacity and the current, ``1/k`` the
resistances and ``k`` times the capacitances: the same voltage, the same SOC.  A filter whose noise
settings are in amps would treat the two differently (a 0.02 A sensor σ is a large error on a
1 Ah cell and nothing on a 50 Ah one); with the noise per C-rate both read the same SOC.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.cell.profile import CellProfile
from service.estimators.ecm2rc_ekf import Ecm2RcEkf
from service.estimators.registry import create
from service.recording import Recording
from tests.test_baselines import TRUE_2RC, _noisy_2rc_drive, make_profile, recording

K_PARALLEL = 20.0


def in_parallel(profile: CellProfile, k: float) -> CellProfile:
    """``k`` copies of the cell in parallel, as one cell."""
    points = [p.model_copy(update={"r_ohm": p.r_ohm / k, "r_ct": p.r_ct / k, "r_df": p.r_df / k,
                                   "c_dl": p.c_dl * k, "c_df": p.c_df * k}) for p in profile.parameters]
    return profile.model_copy(update={"capacity_ah": profile.capacity_ah * k, "parameters": points})


def with_current_times(rec: Recording, k: float) -> Recording:
    return Recording(rec.path, rec.time_s, rec.current_a * k, rec.voltage_v, rec.temperature_c, rec.soc_true)


@pytest.fixture(scope="module")
def drive() -> tuple[Recording, CellProfile, float]:
    t, i, v, soc = _noisy_2rc_drive(3000, seed=3)
    return recording(t, i, v, soc), make_profile(**TRUE_2RC), float(soc[0]) - 0.2


@pytest.mark.parametrize("name", ["ecm2rc-ekf", "fomiukf"])
def test_a_cell_and_the_same_cell_k_times_in_parallel_read_the_same_soc(drive, name: str) -> None:
    rec, profile, soc0 = drive
    estimator = (lambda: Ecm2RcEkf()) if name == "ecm2rc-ekf" else (lambda: create(name))
    one = estimator().run(rec, profile, soc0=soc0)
    many = estimator().run(with_current_times(rec, K_PARALLEL), in_parallel(profile, K_PARALLEL), soc0=soc0)
    np.testing.assert_allclose(many.soc, one.soc, atol=1e-6)
    assert np.sqrt(np.mean((one.soc[600:] - rec.soc_true[600:]) ** 2)) < 0.02  # and it tracks the truth


def test_a_sensor_sigma_in_amps_overrides_the_scale_free_one() -> None:
    from service.estimators.settings import EstimatorSettings

    scale_free = EstimatorSettings()
    in_amps = EstimatorSettings(current_noise_a=0.05, voltage_noise_per_amp_v=0.01)
    cap = np.array([1.0, 50.0])
    np.testing.assert_allclose(scale_free.current_noise_sigma_a(cap), scale_free.current_noise_c * cap)
    np.testing.assert_allclose(scale_free.voltage_noise_per_amp(cap), scale_free.voltage_noise_per_c_v / cap)
    np.testing.assert_allclose(in_amps.current_noise_sigma_a(cap), [0.05, 0.05])
    np.testing.assert_allclose(in_amps.voltage_noise_per_amp(cap), [0.01, 0.01])
