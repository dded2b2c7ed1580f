"""The diffusion signature: relaxation still running at the ends of long rests, over the ohmic
step (:func:`service.diagnosis.signatures.rest_relaxation`), on HPPC-like recordings simulated
with the estimator's own model (:func:`research.validate.simulate_cell`; the drive is
the one of ``tests/test_branch_signature.py``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from research import validate as va
from service.cli import main
from service.diagnosis.signatures import RELAX_MIN_RATIO, RELAX_REST_MIN_S, rest_relaxation
from tests.test_branch_signature import hppc_current

#: a slow solid diffusion: the surface lags the bulk with τ = 3000 s, 0.3 SOC per 1C (steady state)
SLOW = {"extensions": va.Extensions(diffusion_surface=va.SurfaceDiffusionSpec(tau_s=3000.0, gain=0.3))}


def relaxation(case: dict, seed: int = 0, rest_s: float = 1200.0, usable=None) -> dict:
    cols, _ = va.simulate_cell(case, hppc_current(rest_s), seed)
    t, i, v, _ = cols.T
    mask = None if usable is None else usable(t)
    return rest_relaxation(t, i, v, va.CAP, usable=mask)


@pytest.mark.parametrize("seed", [0, 1])
def test_slow_diffusion_is_nominated(seed):
    r = relaxation(SLOW, seed)
    assert r["nominated"], r
    # seven long rests after the 1C discharges, and the closing one after the charge pulse
    assert r["n_rests"] == 8
    assert r["statistic"] >= RELAX_MIN_RATIO and r["z"] >= 5
    # the closing rest follows the charge pulse: its step (a fall) still counts positive
    assert r["step_current_a"][-1] < 0 and r["step_mv"][-1] > 0


@pytest.mark.parametrize("effect", ["none", "hysteresis", "kinetics", "capacity"])
def test_a_cell_that_relaxes_within_minutes_is_not_nominated(effect):
    r = relaxation(va.CASES[effect]["clear"])
    assert r["n_rests"] == 8 and not r["nominated"], r
    assert r["statistic"] < RELAX_MIN_RATIO / 2


def test_only_usable_rests_are_read():
    """The pipeline passes the fit part: a rest that reaches past it is not read."""
    full = relaxation(SLOW)
    first_half = relaxation(SLOW, usable=lambda t: t <= t[0] + 0.5 * (t[-1] - t[0]))
    assert 0 < first_half["n_rests"] < full["n_rests"]
    assert first_half["rest_end_s"] == full["rest_end_s"][: first_half["n_rests"]]
    none = relaxation(SLOW, usable=lambda t: np.zeros(t.size, dtype=bool))
    assert none["n_rests"] == 0 and not none["nominated"] and "fit part" in none["skipped"]


def test_the_rests_read_are_those_of_the_length_asked():
    """min_rest_s: rests of 200 s are read at 120 s, not at the default length (500 s), where only
    the closing rest (600 s) counts; the slow tail is still to come at the end of the short ones."""
    cols, _ = va.simulate_cell(SLOW, hppc_current(200.0), 0)
    t, i, v, _ = cols.T
    short, long_only = rest_relaxation(t, i, v, va.CAP, min_rest_s=120.0), rest_relaxation(t, i, v, va.CAP)
    assert short["n_rests"] == 8 and long_only["n_rests"] == 1, (short["n_rests"], long_only["n_rests"])
    assert short["min_rest_s"] == 120.0 and f"{RELAX_REST_MIN_S:.0f} s" in long_only["what"]
    assert short["nominated"], short


def test_short_rests_give_no_signature():
    r = relaxation(SLOW, rest_s=RELAX_REST_MIN_S / 2)
    # only the closing rest (600 s after the charge pulse's 40 s rest) is long enough
    assert r["n_rests"] == 1


def test_a_nominated_effect_that_misses_its_bar_is_retried_on_the_interleaved_split(tmp_path):
    """pipeline.confirm_nominated: a none verdict with a signature-nominated effect below its bar
    refits that effect alone on the interleaved split and records what it retried; with an
    unreachable bar it is not confirmed there either, and nothing is named. Switched off
    (confirm_split=None) there is no second look."""
    from service.diagnosis.pipeline import DiagnoseOptions, run_diagnosis
    from service.recording import load_recording

    cols, _ = va.simulate_cell(SLOW, hppc_current(1200.0), 0)
    path = tmp_path / "slow_hppc.csv"
    np.savetxt(path, cols, delimiter=",", header="time_s,current_a,voltage_v,temperature_c", comments="", fmt="%.5f")
    rec = load_recording(path)
    quick = {"base_seconds": 8.0, "base_de_maxiter": 8, "effect_seconds": 6.0, "effects": ("diffusion",),
             "min_rel_gain_nominated": 5.0}  # a held-out gain can never reach 500 %
    dg = run_diagnosis(rec, va.user_profile(), DiagnoseOptions(**quick))
    assert dg.signatures["diffusion"]["nominated"], dg.signatures["diffusion"]
    assert dg.verdict == "none"
    conf = dg.protocol["confirmation"]
    assert conf["split"] == "interleaved" and conf["effects"] == ["diffusion"] and conf["confirmed"] == []
    assert conf["heldout_samples"] > 0 and conf["base_rmse_heldout_mv"] > 0
    assert [e.split for e in dg.effects] == ["chronological"]
    off = run_diagnosis(rec, va.user_profile(), DiagnoseOptions(**quick, confirm_split=None))
    assert off.verdict == "none" and "confirmation" not in off.protocol


def test_each_effect_carries_the_split_it_was_scored_on(tmp_path):
    """``socd diagnose --split interleaved``: every effect's figures are the interleaved split's, and
    the JSON and the report say so (the report notes a split only where it differs from the run's)."""
    from service.diagnosis.report import write_report

    dg = _diagnose_diffusion(tmp_path, SLOW, 1200.0, effects=("diffusion", "capacity"), confirm_split=None,
                             split="interleaved")
    assert dg.protocol["split"] == "interleaved"
    assert [e.split for e in dg.effects] == ["interleaved", "interleaved"]
    assert all(e.to_json()["split"] == "interleaved" for e in dg.effects)
    report = write_report(dg, tmp_path / "report").read_text()
    assert "fitted and scored on the" not in report


SYNTHETIC = Path(__file__).resolve().parents[2] / "shared" / "data" / "synthetic"
HPPC_DIFFUSION = "hppc_s105_437525"


@pytest.mark.skipif(not (SYNTHETIC / f"{HPPC_DIFFUSION}.csv").is_file(), reason="shared synthetic data not present")
def test_a_nominated_effect_confirmed_on_the_interleaved_split(tmp_path, capsys):
    """The positive path of the confirmation step, end to end through ``socd diagnose``, on the
    labelled PyBaMM HPPC with slow diffusion (no cheap own-model recording fails the chronological
    split and passes the interleaved one): the rest-relaxation signature nominates diffusion, its
    extension fails the chronological split (the held-out part is the lowest SOC) and is named on
    the interleaved one, and the JSON and the assessment's leads say which split each figure is from."""
    meta = json.loads((SYNTHETIC / f"{HPPC_DIFFUSION}.meta.json").read_text())
    out = tmp_path / "dg.json"
    rc = main(["diagnose", str(SYNTHETIC / f"{HPPC_DIFFUSION}.csv"), "--ocv", str(SYNTHETIC / f"{HPPC_DIFFUSION}_ocv.csv"),
               "--capacity-ah", str(meta["capacity_ah"]), "--effects", "diffusion", "--json", str(out), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    dg = json.loads(out.read_text())
    assert dg["verdict"] == "diffusion", dg["assessment"]["text"]
    top = dg["effects"][0]
    assert top["name"] == "diffusion" and top["significant"] and top["split"] == "interleaved"
    assert top["rmse_after_mv"] < top["rmse_before_mv"]
    conf = dg["protocol"]["confirmation"]
    assert conf["split"] == "interleaved" and conf["confirmed"] == ["diffusion"]
    assert dg["assessment"]["chronological_score"] < 0  # it failed the first split
    leads = dg["assessment"]["signature_without_extension"]
    assert leads and all(d["split"] == "chronological" for d in leads)
    assert next(d for d in leads if d["name"] == "diffusion")["confirmed_on"] == "interleaved"


def _diagnose_diffusion(tmp_path, case: dict, rest_s: float, **options):
    """``case`` on an HPPC with ``rest_s`` rests, diagnosed quickly for diffusion (``options``:
    other or further DiagnoseOptions)."""
    from service.diagnosis.pipeline import DiagnoseOptions, run_diagnosis
    from service.recording import load_recording

    cols, _ = va.simulate_cell(case, hppc_current(rest_s), 0)
    path = tmp_path / f"hppc_{rest_s:.0f}.csv"
    np.savetxt(path, cols, delimiter=",", header="time_s,current_a,voltage_v,temperature_c", comments="", fmt="%.5f")
    quick = {"base_seconds": 8.0, "base_de_maxiter": 8, "effect_seconds": 6.0, "effects": ("diffusion",)}
    return run_diagnosis(load_recording(path), va.user_profile(), DiagnoseOptions(**(quick | options)))


def test_diffusion_is_refused_where_its_signature_read_rests_and_did_not_fire(tmp_path):
    """Effect.needs_signature "where_read": on a cell whose long rests relax within minutes the
    relaxation signature reads them and does not fire, so the surface lag is refused whatever it
    gains (it also fits slow dynamics a clean cell's base circuit lacks: an LFP cell's
    end-of-discharge knee, docs/results/diagnose.md); with no long rest in the fit part there is
    nothing to read, and the voltage fit alone decides."""
    from service.diagnosis.pipeline import SIGNATURE_REQUIRED

    read = _diagnose_diffusion(tmp_path, va.CASES["none"]["clear"], 1200.0)
    sig = read.signatures["diffusion"]
    assert "skipped" not in sig and not sig["nominated"], sig
    reasons = read.outcome("diffusion").reasons
    assert any(r.startswith(SIGNATURE_REQUIRED) for r in reasons) and not read.outcome("diffusion").significant, reasons
    unread = _diagnose_diffusion(tmp_path, SLOW, RELAX_REST_MIN_S / 2)
    assert "skipped" in unread.signatures["diffusion"], unread.signatures["diffusion"]
    assert not any(r.startswith(SIGNATURE_REQUIRED) for r in unread.outcome("diffusion").reasons)
