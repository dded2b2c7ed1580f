"""``socd evaluate --warm-start``: polarisation states driven by the current before the start.

A cell with an hour-long relaxation branch is charged, rests ten minutes and is then
driven for about twenty minutes: started relaxed, a filter reads the charge's leftover
polarisation as SOC; warm, it does not.  Simulated with the model itself, so the truth is exact.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.cell.model import MtsFom
from service.cell.profile import BranchSpec, CellProfile, Extensions, HysteresisSpec, save_profile
from service.cell.trajectory import simulate
from service.cli import main
from service.estimators.ecm2rc_ekf import Ecm2RcEkf, Ecm2RcEkfBank
from service.estimators.pipeline import PackEstimator, foukf
from service.estimators.settings import EstimatorSettings
from service.recording import Recording
from tests.test_fitting import TRUE, nmc_like_ocv

SLOW = BranchSpec(r=0.030, c=3000.0 / 0.030, alpha=1.0)  # R 30 mΩ, τ 50 min


def _profile(**hyst: float) -> CellProfile:
    return CellProfile(capacity_ah=2.0, ocv=nmc_like_ocv(), parameters=[TRUE],
                       hysteresis=HysteresisSpec(**hyst) if hyst else HysteresisSpec(),
                       extensions=Extensions(extra_branches=[SLOW]))


def _charge_rest_drive(seed: int = 0) -> tuple[Recording, int, np.ndarray]:
    """40 min at 1C charge from 20 %, 10 min rest, about 20 min of 0.3-1.5C discharge steps and rests
    (the leftover polarisation is largest early in the drive, so a longer one only dilutes it).

    Returns the recording, the index of the start point (end of the rest) and true SOC."""
    rng = np.random.default_rng(seed)
    cur = [np.full(2400, -2.0), np.zeros(600)]
    for _ in range(24):
        cur.append(np.full(int(rng.integers(20, 80)), float(rng.choice([0.6, 1.5, 3.0, 0.0]))))
    i = np.concatenate(cur)
    t = np.arange(i.size, dtype=float)
    prof = _profile()
    v, soc = simulate(prof, t, i, np.full(t.size, 25.0), 0.2)
    v = v + rng.normal(0.0, 1e-3, v.size)
    return Recording(Path("charge_rest_drive.csv"), t, i, v, np.full(t.size, 25.0)), 3000, soc


def test_warm_start_sets_the_model_state_and_leaves_soc_alone():
    rec, start, _ = _charge_rest_drive()
    prof = _profile(u_h_max_v=0.02, rate=50.0)
    history = rec.slice(0, start + 1)
    est = PackEstimator(prof, 3, EstimatorSettings())
    est.start(np.array([0.3, 0.5, 0.7]))
    sigma = est.soc_std.copy()
    est.warm_start(history, cells=np.array([True, True, False]))

    model = MtsFom(prof, prof.parameters_at(np.full(3, 25.0)), np.full(3, 0.5), est.settings.memory_length)
    dt = history.dt_s()
    for k in range(len(history)):
        model.step(dt[k], np.full(3, history.current_a[k]), np.full(3, 25.0))
    b = prof.n_branches
    np.testing.assert_allclose(est.ukf.x[:2, :b], model.history[:2, :, 0], atol=1e-12)
    np.testing.assert_allclose(est.ukf.hist[:2], model.history[:2], atol=1e-12)
    np.testing.assert_allclose(est.ukf.x[:2, est.ukf.i_uh], model.u_h[:2], atol=1e-12)
    # the slow branch still holds the charge: -R I (1 - e^(-2400/τ)) e^(-600/τ) = -27 mV
    assert -0.030 < est.ukf.x[0, 2] < -0.024
    assert est.ukf.x[0, est.ukf.i_uh] > 0.019  # charged: on the charge branch
    # the unselected cell and every SOC and σ are untouched
    np.testing.assert_array_equal(est.ukf.x[2, :b], 0.0)
    np.testing.assert_array_equal(est.soc, [0.3, 0.5, 0.7])
    np.testing.assert_array_equal(est.soc_std, sigma)


def test_warm_start_removes_the_leftover_polarisation_error():
    rec, start, soc_true = _charge_rest_drive()
    part, truth = rec.slice(start), soc_true[start:]
    prof = _profile()
    history = rec.slice(0, start + 1)
    errs = {}
    for warm in (False, True):
        trace = foukf().run(part, prof, float(truth[0]) - 0.2, history=history if warm else None)
        late = part.time_s - part.time_s[0] >= 600
        errs[warm] = float(np.sqrt(np.mean((trace.soc[late] - truth[late]) ** 2)))
    # relaxed, the filter takes the branch's -27 mV for SOC; warm, it does not
    assert errs[False] > 0.005
    assert errs[True] < 0.002
    assert errs[True] < errs[False] / 4, errs


def test_ekf_warm_start_follows_its_rc_recursion():
    rec, start, soc_true = _charge_rest_drive()
    history = rec.slice(0, start + 1)
    prof = _profile()
    bank = Ecm2RcEkfBank(prof, 0.5, 25.0)
    bank.warm_start(history)
    tau = np.power(TRUE.r_ct * TRUE.c_dl, 1 / TRUE.m), np.power(TRUE.r_df * TRUE.c_df, 1 / TRUE.n)
    u = np.zeros(2)
    dt = history.dt_s()
    for k in range(len(history)):
        a = np.exp(-dt[k] / np.array(tau))
        u = a * u + np.array([TRUE.r_ct, TRUE.r_df]) * (1 - a) * history.current_a[k]
    np.testing.assert_allclose(bank.x[0, 1:], u, rtol=1e-9, atol=1e-12)
    assert bank.soc[0] == 0.5
    # and the offline estimator accepts the history
    part = rec.slice(start)
    trace = Ecm2RcEkf().run(part, prof, float(soc_true[start]) - 0.2, history=history)
    assert np.isfinite(trace.soc).all()


def test_evaluate_warm_start_flag_end_to_end(tmp_path: Path, capsys) -> None:
    """Through ``socd evaluate``: the flag is recorded in the JSON and lowers the pipeline's
    error on the charge-rest-drive recording; the default run is the relaxed start."""
    rec, start, soc_true = _charge_rest_drive()
    csv = tmp_path / "charge_rest_drive.csv"
    rows = np.column_stack([rec.time_s, rec.current_a, rec.voltage_v, rec.temperature_c, soc_true])
    np.savetxt(csv, rows, delimiter=",", header="time_s,current_a,voltage_v,temperature_c,soc_true",
               comments="", fmt="%.6f")
    cell = tmp_path / "cell.toml"
    save_profile(_profile(), cell)
    scores = {}
    for flag in ([], ["--warm-start"]):
        out = tmp_path / f"res{len(flag)}.json"
        rc = main(["evaluate", str(csv), "--cell", str(cell), "--full-at", str(rec.time_s[start]),
                   "--estimator", "foukf", "--json", str(out), "--quiet", *flag])
        assert rc == 0, capsys.readouterr().err
        doc = json.loads(out.read_text())
        assert doc["warm_start"] is bool(flag)
        scores[bool(flag)] = doc["results"][0]["soc_rmse_after_600s_pct"]
    assert scores[True] < scores[False] / 4, scores
