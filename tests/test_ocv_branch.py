"""An OCV table that is one hysteresis branch (``HysteresisSpec.table_branch``).

LFP cells often have only a charge-curve OCV test.  The profile says so, the model reads
its mean as ``table - U_H`` and ``U_h`` then runs from ``+U_H`` (just charged: on the
table) to ``-U_H`` (after discharge: ``2 U_H`` below it).  ``socd fit --ocv-branch``
fits the half-gap with every segment starting on the branch of its history.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.cell.fitting import (
    FitSegment,
    excited_window,
    fit_parameters,
    last_current_direction,
)
from service.cell.profile import CellProfile, HysteresisSpec, OcvSpec
from service.cell.trajectory import simulate, simulate_batch
from service.characterisation.characterise import split_at_rests
from service.recording import Recording
from tests.test_fitting import TRUE as POINT


def lfp_like_table() -> OcvSpec:
    soc = np.linspace(0, 1, 41)
    ocv = 3.30 + 0.05 * soc - 0.3 * np.exp(-soc / 0.04) + 0.15 * np.exp((soc - 1) / 0.03)
    return OcvSpec(soc=soc.tolist(), ocv_v=[ocv.tolist()])


def lfp(u_h: float = 0.02, branch: str = "charge", rate: float = 40.0) -> CellProfile:
    return CellProfile(capacity_ah=1.0, ocv=lfp_like_table(), parameters=[POINT],
                       hysteresis=HysteresisSpec(u_h_max_v=u_h, rate=rate, table_branch=branch))


def test_the_model_reads_the_mean_below_a_charge_table_and_sits_on_it_after_a_charge():
    soc = np.linspace(0.0, 1.0, 201)
    at25 = np.full(soc.shape, 25.0)
    raw = lfp(0.0, "mean").ocv_table().ocv(soc, at25)   # the table as written
    for branch, sign in (("charge", 1.0), ("discharge", -1.0), ("mean", 0.0)):
        table = lfp(0.02, branch).ocv_table()
        assert np.allclose(table.ocv(soc, at25), raw - sign * 0.02, atol=1e-12)
    # a charge to 0.6, a rest, a discharge to 0.3, a rest: rest voltages on the charge table, then 2 U_H below
    t = np.arange(5000, dtype=float)
    i = np.zeros(t.size)
    i[100:1180] = -1.0          # 0.3 of capacity charged
    i[2500:3580] = 1.0          # 0.3 discharged
    v, s = simulate(lfp(0.02, "charge"), t, i, np.full(t.size, 25.0), 0.3)
    on_table = np.interp(s[2400], soc, raw)
    assert v[2400] == pytest.approx(on_table, abs=2e-4)
    assert v[4900] == pytest.approx(np.interp(s[4900], soc, raw) - 0.04, abs=2e-4)


def test_a_candidate_u_h_moves_the_mean_by_its_difference_from_the_profiles():
    """The fit's candidates vary U_H against a profile whose table holds another U_H: the batch
    simulation must equal a profile that carries the candidate's U_H, branch start included."""
    t = np.arange(1500, dtype=float)
    rng = np.random.default_rng(4)
    i = np.repeat(rng.choice([1.0, 0.5, 0.0, -0.5], size=30), 50)
    temp = np.full(t.size, 25.0)
    template = lfp(0.0, "charge")
    params = template.parameters_at(25.0, n_cells=3)
    params.u_h_max = np.array([0.0, 0.015, 0.03])
    v, _ = simulate_batch(template, t, i, temp, np.full(3, 0.9), params, u_h0_branch=1.0)
    for k, u in enumerate(params.u_h_max):
        v_ref, _ = simulate(lfp(float(u), "charge"), t, i, temp, 0.9, u_h0=float(u))
        assert np.max(np.abs(v[:, k] - v_ref)) < 1e-12


def test_segments_start_on_the_branch_of_their_history():
    assert last_current_direction(np.array([0.0, 1.0, 1.0, 0.0]), 0.05) == -1.0
    assert last_current_direction(np.array([1.0, -0.5, 0.01]), 0.05) == 1.0
    assert last_current_direction(np.zeros(4), 0.05) == 0.0
    # a full-charge cut: the first segment on the charge branch, one after a discharge and a rest on the other
    n = 3000
    t = np.arange(n, dtype=float)
    i = np.zeros(n)
    i[10:1000] = 1.0
    i[1800:2600] = 1.0
    rec = Recording(path=Path("synthetic.csv"), time_s=t, current_a=i, voltage_v=np.full(n, 3.3),
                    temperature_c=np.full(n, 25.0))
    soc = 1.0 - np.cumsum(i) / 3600.0
    segs = split_at_rests(rec, soc, 1.0, track_branch=True)
    assert [s.u_h0_branch for s in segs] == [1.0, -1.0]
    # a mean table keeps the fits' old start, U_h = 0 (the bundled A123 profile's)
    assert [s.u_h0_branch for s in split_at_rests(rec, soc, 1.0)] == [0.0, 0.0]
    for branch, later in ((1.0, -1.0), (0.0, 0.0)):
        seg = FitSegment(t, i, np.full(n, 3.3), np.full(n, 25.0), soc0=1.0, u_h0_branch=branch)
        w = excited_window(seg, 1000, 1.0)
        assert w.time_s[0] > 0
        assert w.u_h0_branch == later


def test_fit_recovers_the_half_gap_of_a_charge_branch_table():
    t = np.arange(3000, dtype=float)
    rng = np.random.default_rng(5)
    i = np.repeat(rng.choice([1.5, 1.0, 0.5, 0.0, -0.5], size=60), 50)
    i[:60] = 0.0
    temp = np.full(t.size, 25.0)
    truth = lfp(0.025, "charge", rate=30.0)
    v, _ = simulate(truth, t, i, temp, 0.98, u_h0=0.025)
    v = v + rng.normal(0, 0.001, t.size)
    res = fit_parameters(lfp(0.0, "charge"), [FitSegment(t, i, v, temp, soc0=0.98, u_h0_branch=1.0)],
                         fit_hysteresis=True, max_seconds=120, x0=POINT, de_maxiter=15)
    assert res.hysteresis is not None and res.hysteresis.table_branch == "charge"
    assert res.hysteresis.u_h_max_v == pytest.approx(0.025, abs=0.006)
    assert res.rmse_mv < 1.5


def test_socd_fit_refuses_a_branch_without_the_hysteresis(tmp_path):
    csv = tmp_path / "drive.csv"
    n = 400
    rows = ["time_s,current_a,voltage_v,temperature_c"] + [f"{k},{1.0 if 50 <= k < 300 else 0.0},3.3,25.0"
                                                          for k in range(n)]
    csv.write_text("\n".join(rows) + "\n")
    out = subprocess.run([sys.executable, "-m", "service.cli", "fit", str(csv), "--capacity-ah", "1.0",
                          "--ocv-branch", "charge", "-o", str(tmp_path / "p.toml")], check=False, capture_output=True, text=True)
    assert out.returncode != 0
    assert "--hysteresis" in out.stderr
    assert not (tmp_path / "p.toml").exists()
