"""``socd fit --candidates``: of profiles fitted with different optimiser seeds, the one whose
``fomiukf`` reads the fit recordings' SOC best is written (service.characterisation.profile_pick)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from service.cell.profile import load_profile
from service.characterisation.characterise import PoorFitError, ecm_start_point
from service.characterisation.fit_summary import (
    PICKED_TWO_RC_SOURCE,
    FitSummary,
    TemperatureSummary,
    with_picked_two_rc,
)
from service.characterisation.profile_pick import (
    DEFAULT_CANDIDATES,
    FitFileScore,
    describe_pick,
    describe_reference_two_rc,
    fit_file_score,
    pick_profile,
    reference_two_rc_variant,
    scored_recordings,
)
from service.cli import main
from service.commands.fit import Candidate, choose, fit_report
from service.commands.progress import Bar
from service.recording import load_recording
from tests.conftest import NMC_CAPACITY_AH, NMC_PARAMETERS, TAU_CT_S, TAU_DF_S
from tests.test_ocv_tests import write_ocv_test


def test_the_fit_file_score_is_socd_evaluates_mean_on_the_fit_recordings_but_the_ocv_tests(
        tmp_path: Path, nmc_recording, nmc_profile_file: Path) -> None:
    """The score is what ``socd evaluate --estimator fomiukf`` reads on the same files with its
    defaults (the research table fit_file_pick measured the rule that way); an OCV test among
    the fit recordings is left out.  Both score the profile as saved (12 significant digits: the
    score of a tiny SOC error moves by parts in 1e9 with the last digits)."""
    drives = [nmc_recording(name=f"drive{k}", duration_s=900, seed=k, soc0=0.9) for k in (1, 2)]
    ocv_test = write_ocv_test(tmp_path / "ocv25.csv", 25.0, 0.0)
    recs = [load_recording(ocv_test), *(load_recording(d.path) for d in drives)]
    kept, full = scored_recordings(recs, [None] * 3, NMC_CAPACITY_AH)
    assert [r.name for r in kept] == ["drive1", "drive2"] and full == [None, None]

    got = fit_file_score(load_profile(nmc_profile_file), 7, kept, full)
    out = tmp_path / "eval.json"
    assert main(["evaluate", *(str(d.path) for d in drives), "--cell", str(nmc_profile_file), "--estimator",
                 "fomiukf", "--no-bar", "-q", "--json", str(out)]) == 0
    rmse = [r["soc_rmse_after_600s_pct"] for r in json.loads(out.read_text())["results"]]
    assert got.seed == 7 and got.recordings_scored == 2
    assert got.soc_rmse_after_600s_pct == pytest.approx(sum(rmse) / 2, rel=1e-9)


def test_the_pick_keeps_the_lowest_reading_and_the_first_of_equals_or_of_the_unscored(nmc_profile) -> None:
    a, b, c = (nmc_profile.model_copy(update={"name": n}) for n in "abc")
    assert pick_profile([(a, FitFileScore(0, 0.9, 2)), (b, FitFileScore(1, 0.4, 2)), (c, FitFileScore(2, 0.6, 2))])[0] is b
    assert pick_profile([(a, FitFileScore(0, 0.5, 1)), (b, FitFileScore(1, 0.5, 1))])[0] is a
    assert pick_profile([(a, FitFileScore(0, None, 0)), (b, FitFileScore(1, 0.7, 1))])[0] is b
    assert pick_profile([(a, FitFileScore(0, None, 0)), (b, FitFileScore(1, None, 0))])[0] is a
    with pytest.raises(ValueError, match="no candidate"):
        pick_profile([])
    line = describe_pick([FitFileScore(3, None, 0), FitFileScore(4, None, 0)], FitFileScore(3, None, 0))
    assert "none scores the 2 candidates" in line and "keeping seed 3's" in line


def test_where_the_quality_check_refuses_every_candidate_the_first_refusal_is_raised(nmc_profile) -> None:
    import argparse

    log = fit_report(argparse.Namespace(quiet=True), Bar(None, None))
    first, second = PoorFitError("25 °C: seed 0 poor"), PoorFitError("25 °C: seed 1 poor")
    with pytest.raises(PoorFitError, match="seed 0 poor"):
        choose([Candidate(0, nmc_profile, first, log), Candidate(1, nmc_profile, second, log)], [], [], log, Bar(None, None))


def test_socd_fit_writes_the_candidate_whose_filter_reads_the_fit_recordings_best(
        tmp_path: Path, nmc_recording, nmc_ocv_csv: Path, capsys) -> None:
    """With the default two candidates the log gives each seed's reading and the seed kept; the profile
    written is the lowest reading's (scored again here, it reads what the log says) and its notes keep
    the line. With --starts 2 each candidate runs two searches per temperature, so the second candidate
    starts two seeds on (6 and 7 after 4 and 5): no search is run twice."""
    assert DEFAULT_CANDIDATES == 2
    drive = nmc_recording(name="drive", duration_s=900, seed=3, soc0=0.95)
    out, report = tmp_path / "cell.toml", tmp_path / "fit.json"
    assert main(["fit", str(drive.path), "--ocv", str(nmc_ocv_csv), "--capacity-ah", str(NMC_CAPACITY_AH),
                 "--max-seconds", "2", "--force", "--seed", "4", "--starts", "2", "-o", str(out),
                 "--report", str(report)]) == 0
    err = capsys.readouterr().err
    assert "candidate profile 2 of 2: the fit again with optimiser seed 6 (the first used 4)" in err
    assert re.findall(r"search \d of 2 \(seed (\d)\)", err) == ["4", "5", "6", "7"], err
    m = re.search(r"profile pick: .*: seed 4 ([\d.]+) %, seed 6 ([\d.]+) %; keeping seed (\d)'s; seed \d's profile "
                  r"with its 25 °C point the textbook 2-RC point \(no hysteresis\) reads ([\d.]+) %; "
                  r"(writing that point|keeping the fitted point)", err)
    assert m, err
    readings = {4: float(m.group(1)), 6: float(m.group(2))}
    kept, two_rc = int(m.group(3)), float(m.group(4))
    assert readings[kept] == min(readings.values())
    written = load_profile(out)
    again = fit_file_score(written, kept, [load_recording(drive.path)], [None])
    assert round(again.soc_rmse_after_600s_pct, 2) == pytest.approx(min(readings[kept], two_rc), abs=0.006)
    # the profile keeps the pick's readings and the seed kept after the log is gone
    assert written.notes["profile_pick"] == m.group(0).removeprefix("profile pick: ")
    # --report says the same by machine: both candidates, their readings, which one the profile is
    summary = FitSummary.load(report)
    assert summary.profile == str(out) and summary.profile_pick == written.notes["profile_pick"]
    assert [c.seed for c in summary.candidates] == [4, 6] and summary.written().seed == kept
    assert {c.seed: round(c.fit_file_soc_rmse_after_600s_pct, 2) for c in summary.candidates} == readings
    assert round(summary.written().reference_two_rc_soc_rmse_after_600s_pct, 2) == two_rc
    w = summary.written()
    assert w.reference_two_rc_written == (m.group(5) == "writing that point")
    assert w.reference_two_rc_written == (w.reference_two_rc_soc_rmse_after_600s_pct < w.fit_file_soc_rmse_after_600s_pct)
    assert all(c.reference_two_rc_soc_rmse_after_600s_pct is None for c in summary.candidates if not c.written)
    for c in summary.candidates:
        assert [t.temp_c for t in c.temperatures] == [25.0] and c.refusal is None
        assert any(f"seed {c.seed}" in line for line in c.log), "each candidate keeps its own log"
        # the written point's source says whether the pick replaced the fitted one
        picked = c.written and w.reference_two_rc_written
        assert (c.temperatures[0].source == PICKED_TWO_RC_SOURCE) == picked, c.temperatures[0].source


def test_the_report_names_the_picked_2rc_point_at_the_reference_temperature_only() -> None:
    """Only the temperature nearest 25 °C (the one the variant replaces) changes its source."""
    def summary(t: float) -> TemperatureSummary:
        return TemperatureSummary(temp_c=t, rmse_mv=5.0, ecm_rmse_mv=6.0, ecm_simulated_mv=6.5,
                                  overpotential_rms_mv=40.0, unexplained_share=0.125, source="fractional fit",
                                  at_bounds=["n = 1 (upper bound)"], ocv_measured=True, problem=None)

    got = with_picked_two_rc([summary(t) for t in (0.0, 10.0, 30.0, 45.0)])
    assert [t.source for t in got] == ["fractional fit", "fractional fit", PICKED_TWO_RC_SOURCE, "fractional fit"]
    assert got[2].rmse_mv == 5.0 and got[2].at_bounds == ["n = 1 (upper bound)"], "the fit's figures stay"
    assert with_picked_two_rc([]) == []


def test_where_the_evaluation_refuses_a_fit_recordings_truth_the_first_candidate_is_written(
        tmp_path: Path, nmc_profile, capsys) -> None:
    """A recording the scoring cannot count a truth on (here a 1C discharge for three hours of a 2 Ah
    cell) leaves the pick without a reading; the fit is not failed for it: the first candidate is
    written and a notice says why."""
    import argparse

    import numpy as np

    from tests.conftest import write_recording_csv

    t = np.arange(0.0, 3 * 3600.0, 10.0)
    path = write_recording_csv(tmp_path / "overrun.csv", t, np.full(t.size, 2.0), np.full(t.size, 3.7),
                               np.full(t.size, 25.0))
    first, second = (nmc_profile.model_copy(update={"name": n}) for n in ("first", "second"))
    log = fit_report(argparse.Namespace(quiet=True), Bar(None, None))
    got = choose([Candidate(0, first, None, log), Candidate(1, second, None, log)], [load_recording(path)], [None],
                 log, Bar(None, None))
    assert got.seed == 0 and got.readings == {}
    assert got.profile.name == "first" and "cannot be scored" in got.profile.notes["profile_pick"]
    assert "cannot be scored" in capsys.readouterr().err and "keeping seed 0's" in log.lines[-1]


def _with_two_rc(profile, r_scale: float = 1.0):
    """``profile`` with a stored textbook 2-RC fit at each of its temperatures: the synthetic cell's
    resistances and time constants (``r_scale`` times the branch resistances) and its OCV."""
    from service.cell.profile import Ecm2RcPoint, Ecm2RcSpec
    from tests.conftest import NMC_PARAMETERS, TAU_CT_S, TAU_DF_S

    p = NMC_PARAMETERS
    points = [Ecm2RcPoint(temp_c=q.temp_c, r0=p["r_ohm"], r1=p["r_ct"] * r_scale, tau1_s=TAU_CT_S,
                          r2=p["r_df"] * r_scale, tau2_s=TAU_DF_S) for q in profile.parameters]
    return profile.model_copy(update={"ecm2rc": Ecm2RcSpec(ocv=profile.ocv, points=points)})


def test_the_reference_two_rc_variant_sets_only_the_point_nearest_25c(nmc_profile_factory) -> None:
    """The variant the pick reads last: the point nearest 25 °C is the stored 2-RC point in the
    fractional form (orders 1, C = τ/R), the others stay; none without a 2-RC fit, and none where
    the reference point already is the 2-RC point."""

    fractional = nmc_profile_factory(temps_c=(10.0, 23.0, 40.0))
    assert reference_two_rc_variant(fractional) is None
    profile = _with_two_rc(fractional)
    variant = reference_two_rc_variant(profile)
    assert variant is not None
    cold, ref, warm = variant.parameters
    assert cold == profile.parameters[0] and warm == profile.parameters[2]
    assert ref.temp_c == 23.0 and ref.m == 1.0 and ref.n == 1.0
    assert ref.r_ct == pytest.approx(NMC_PARAMETERS["r_ct"]) and ref.r_ct * ref.c_dl == pytest.approx(TAU_CT_S)
    assert ref.r_df * ref.c_df == pytest.approx(TAU_DF_S)
    already = profile.model_copy(update={"parameters": [
        ecm_start_point(e, e.temp_c) if e.temp_c == 23.0 else q for e, q in zip(profile.ecm2rc.points, profile.parameters)]})
    assert reference_two_rc_variant(already) is None
    line = describe_reference_two_rc(FitFileScore(2, 0.5, 1), FitFileScore(2, None, 0), 23.0, False)
    assert line == ("seed 2's profile with its 23 °C point the textbook 2-RC point could not be scored; "
                    "keeping the fitted point")


@pytest.mark.parametrize("truth", ["two_rc", "fractional"])
def test_the_pick_writes_the_reference_two_rc_point_only_where_the_filter_reads_the_fit_recordings_better_on_it(
        tmp_path: Path, nmc_recording, nmc_profile_factory, truth: str) -> None:
    """A recording made by a 2-RC cell (orders 1) is read better on the stored 2-RC point than on a
    fractional fit that missed it, so that point is written; made by the fractional cell, whose 2-RC
    fit is off (branch resistances three times too large), the fitted point stays. Both
    readings are in the pick's note and in the summary fields."""
    import argparse

    from tests.conftest import TAU_CT_S, TAU_DF_S

    if truth == "two_rc":
        drive = nmc_recording(name="drive", duration_s=1000, seed=5, soc0=0.9, m=1.0, n=1.0,
                              c_dl=TAU_CT_S / 0.01, c_df=TAU_DF_S / 0.02)
        fitted = _with_two_rc(nmc_profile_factory(r_ct=0.03, m=0.5, r_df=0.06, n=0.5))
    else:
        drive = nmc_recording(name="drive", duration_s=1000, seed=5, soc0=0.9)
        fitted = _with_two_rc(nmc_profile_factory(), r_scale=3.0)
    log = fit_report(argparse.Namespace(quiet=True), Bar(None, None))
    got = choose([Candidate(0, fitted, None, log), Candidate(1, fitted, None, log)], [load_recording(drive.path)],
                 [None], log, Bar(None, None))
    note = got.profile.notes["profile_pick"]
    assert got.reference_two_rc is not None and got.readings[0] is not None
    assert "with its 25 °C point the textbook 2-RC point (no hysteresis) reads" in note, note
    if truth == "two_rc":
        assert got.reference_two_rc < got.readings[0] and got.reference_two_rc_written
        assert got.profile.parameters[0].m == 1.0 and "writing that point" in note
    else:
        assert got.reference_two_rc > got.readings[0] and not got.reference_two_rc_written
        assert got.profile.parameters == fitted.parameters and "keeping the fitted point" in note
