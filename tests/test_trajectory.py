"""The array-wise simulation along a recording (service.cell.trajectory) equals stepping
the model one sample at a time (MtsFom.step through service.cell.model.drive)."""

from __future__ import annotations

import numpy as np
import pytest
from test_fitting import nmc_like_ocv, pulse_current

from service.cell.fractional import cpe_step, gl_weights, push_history
from service.cell.model import MtsFom, drive
from service.cell.profile import (
    ArrheniusSpec,
    CellProfile,
    Extensions,
    HysteresisSpec,
    ParameterPoint,
    SocResistanceSpec,
    SurfaceDiffusionSpec,
)
from service.cell.trajectory import cpe_trajectory, simulate, simulate_batch

POINT = ParameterPoint(r_ohm=0.03, r_ct=0.015, c_dl=300.0, m=0.9, r_df=0.02, c_df=9000.0, n=0.85)
COLD = ParameterPoint(temp_c=0.0, r_ohm=0.06, r_ct=0.04, c_dl=200.0, m=0.8, r_df=0.05, c_df=6000.0,
                      n=0.7)


def stepwise(prof: CellProfile, t, i, temp, soc0: float, u_h0: float = 0.0) -> tuple:
    """The reference: ``MtsFom.step`` sample by sample, following the temperature as
    :func:`simulate` does."""
    params = prof.parameters_at(float(temp[0]), n_cells=1)
    model = MtsFom(prof, params, np.array([soc0]), u_h0=np.array([u_h0]))
    follow = len(prof.parameters) > 1 or prof.extensions.arrhenius is not None
    v, soc = drive(model, t, i, temp, follow_temperature=follow)
    return v[:, 0], soc[:, 0]


def irregular_time(n: int, seed: int) -> np.ndarray:
    """1-s samples with a jittered stretch, a 0.1-s burst and two logging gaps."""
    rng = np.random.default_rng(seed)
    dt = np.ones(n)
    dt[n // 5:n // 5 + 60] = 1.0 + rng.uniform(-0.02, 0.02, dt[n // 5:n // 5 + 60].size)
    dt[n // 2:n // 2 + 40] = 0.1
    dt[2 * n // 3] = 120.0
    dt[3 * n // 4] = 7.0
    return np.concatenate([[0.0], np.cumsum(dt[1:])])


def _profile(**extensions) -> CellProfile:
    return CellProfile(capacity_ah=2.0, ocv=nmc_like_ocv(), parameters=[COLD, POINT],
                       hysteresis=HysteresisSpec(u_h_max_v=0.015, rate=30.0),
                       extensions=Extensions(**extensions))


CASES = {
    "base": {},
    "bias_kinetics_arrhenius": dict(current_bias_a=0.03, capacity_scale=0.95, kinetics_i0_a=1.5,
                                    arrhenius=ArrheniusSpec(ref_temp_c=25.0, ea_r_ohm_j_mol=2e4,
                                                            ea_r_ct_j_mol=4e4,
                                                            entropic_v_per_k=1e-4)),
    "surface_lag": dict(diffusion_surface=SurfaceDiffusionSpec(tau_s=400.0, gain=0.06)),
    "soc_resistance": dict(soc_resistance=SocResistanceSpec(
        soc=[0.0, 0.2, 0.6, 1.0], temps_c=[0.0, 25.0], r_ohm_scale=[[1.5, 1.1, 1.0, 1.2]] * 2,
        r_pol_scale=[[3.0, 1.5, 0.9, 1.3], [2.0, 1.2, 1.0, 1.1]])),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_simulate_equals_stepping_the_model(case):
    prof = _profile(**CASES[case])
    n = 1500
    t = irregular_time(n, 1)
    i = pulse_current(n, 2.0, 4)
    temp = np.minimum(np.linspace(5.0, 40.0, n), 25.0)  # re-read along the ramp, then held
    v_ref, soc_ref = stepwise(prof, t, i, temp, 0.9, u_h0=-0.01)
    v, soc = simulate(prof, t, i, temp, 0.9, u_h0=-0.01)
    assert np.max(np.abs(v - v_ref)) < 1e-10
    assert np.max(np.abs(soc - soc_ref)) < 1e-12


def test_simulate_equals_stepping_with_an_exchange_current_per_temperature():
    """A profile characterised with i0 at each temperature: along a temperature ramp each stretch's
    Butler-Volmer term is its own parameters', whose linear part is in that stretch's R_ohm (with the
    last stretch's i0 on every sample, the two parts no longer cancel and a large pulse in a warming
    cell read hundreds of mV off)."""
    cold = COLD.model_copy(update={"r_ohm": 0.1, "i0_a": 0.3})
    prof = CellProfile(capacity_ah=2.0, ocv=nmc_like_ocv(), parameters=[cold, POINT.model_copy(update={"i0_a": 3.0})])
    n = 1500
    t = irregular_time(n, 3)
    i = pulse_current(n, 6.0, 4)
    temp = np.linspace(0.0, 20.0, n)
    v_ref, soc_ref = stepwise(prof, t, i, temp, 0.9)
    v, soc = simulate(prof, t, i, temp, 0.9)
    assert np.max(np.abs(v - v_ref)) < 1e-10
    assert np.max(np.abs(soc - soc_ref)) < 1e-12


def test_batch_candidates_each_equal_their_own_model():
    """Three candidates with different branch orders and resistances in one call."""
    prof = _profile()
    n = 1200
    t = irregular_time(n, 2)
    i = pulse_current(n, 2.0, 5)
    temp = np.full(n, 25.0)
    params = prof.parameters_at(25.0, n_cells=3)
    params.r[:, 0] *= np.array([0.5, 1.0, 2.0])
    params.alpha[:, 1] = np.array([0.5, 0.75, 1.0])
    v, soc = simulate_batch(prof, t, i, temp, np.array([0.9, 0.8, 0.7]), params)
    model = MtsFom(prof, params, np.array([0.9, 0.8, 0.7]))
    ref_v, ref_soc = drive(model, t, i, temp, follow_temperature=False)
    assert np.max(np.abs(v - ref_v)) < 1e-10
    assert np.max(np.abs(soc - ref_soc)) < 1e-12


@pytest.mark.parametrize("steps", [10, 700])  # stepped directly, and solved as one banded system
def test_cpe_trajectory_equals_the_step_and_leaves_the_end_history(steps):
    rng = np.random.default_rng(7)
    n, b, length = 3, 2, 16
    r = rng.uniform(0.005, 0.05, (n, b))
    c = rng.uniform(50.0, 5000.0, (n, b))
    alpha = rng.uniform(0.4, 1.0, (n, b))
    weights = gl_weights(alpha, length)
    history = rng.normal(0.0, 0.01, (n, b, length))
    current = rng.normal(0.0, 2.0, (steps, n))
    dt = np.diff(irregular_time(steps + 1, 3))
    ref_history = history.copy()
    ref = np.empty((steps, n, b))
    for k in range(steps):
        ref[k] = cpe_step(ref_history, current[k][:, None], dt[k], r, c, alpha, weights)
        push_history(ref_history, ref[k])
    out = cpe_trajectory(current, dt, r, c, alpha, weights, history)
    assert np.max(np.abs(out - ref)) < 1e-12
    assert np.max(np.abs(history - ref_history)) < 1e-12


def test_bench_simulate_reports_throughput_and_agrees_with_stepping(capsys):
    """`socd bench --simulate` (the bundled profile): both rates and the voltage difference of
    the two simulations on the same inputs, as JSON. Only the agreement is asserted; speed
    is for the benchmark to report, not for a test to time."""
    import json

    from service.cli import main

    rc = main(["bench", "--simulate", "--cells", "3", "--steps", "300", "--reference-steps", "80",
               "--json", "-"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    result = json.loads(captured.out)
    assert result["candidates"] == 3 and result["steps"] == 300 and result["reference_steps"] == 80
    assert result["samples_per_s"] > 0 and result["reference_samples_per_s"] > 0
    assert result["max_abs_diff_v"] < 1e-9
    assert main(["bench", "--simulate", "--latency"]) == 2
    assert "two different measurements" in capsys.readouterr().err
