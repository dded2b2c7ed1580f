"""Of profiles fitted with different optimiser seeds, keep the one whose filter reads its own fit
recordings' SOC best.

Where the data pin a cell's parameters down loosely, global searches seeded differently end on
points that fit the voltage alike yet estimate SOC differently. The fit recordings' truth SOC is
known (that is what makes them fit recordings), so each candidate's ``fomiukf`` is run on them with
the protocol of DESIGN §7 (a ±20 % wrong start, scored after 600 s) and the lowest mean SOC RMSE
is kept. No recording outside the fit decides it. ``socd fit``'s default of two candidates was
chosen leave-one-cell-out over nine cells (docs/results/characterisation.md, fit_file_pick).
OCV tests are left out of the score: the slow test the OCV is read from says nothing about the
dynamic model's choice, and would dominate the run time.

The profile kept is then read once more with its reference temperature's point set to the textbook
2-RC point ``socd fit`` stores beside it (:func:`reference_two_rc_variant`): the model the bar runs on,
in the fractional form. Where the filter reads the fit recordings better on that, the fractional
search found nothing there the filter can use, and the 2-RC point is written. Only the reference
point: set at every temperature, the same reading picked the 2-RC points of the Panasonic cell's cold
pulse tests, whose drives then read far worse (docs/results/characterisation.md,
two_rc_point_by_fit_file).
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the fitting and filtering parts load scipy: imported where used, so `socd --help` stays quick
    from service.cell.profile import CellProfile
    from service.recording import Recording

#: the estimator whose SOC error on the fit recordings picks the profile
PICK_ESTIMATOR = "fomiukf"
#: profiles fitted by default, seeded --seed, --seed + 1, ... (chosen as the module docstring says)
DEFAULT_CANDIDATES = 2
#: how the pick's lines begin in the fit log; the profile's ``notes.profile_pick`` holds the rest
PICK_LOG_PREFIX = "profile pick: "


@dataclass(frozen=True)
class FitFileScore:
    """One candidate profile read on the fit recordings: its seed, the mean SOC RMSE after 600 s
    [%] over the recordings scored (``None`` where none lasts 600 s past its start) and how many."""

    seed: int
    soc_rmse_after_600s_pct: float | None
    recordings_scored: int


def scored_recordings(recordings: Sequence[Recording], full_at: Sequence[str | float | None],
                      capacity_ah: float) -> tuple[list[Recording], list[str | float | None]]:
    """The fit recordings the pick reads (every one but the OCV tests) and their full-charge points."""
    from service.characterisation.ocv_sources import is_ocv_test

    kept = [(r, fa) for r, fa in zip(recordings, full_at) if not is_ocv_test(r, capacity_ah)]
    return [r for r, _ in kept], [fa for _, fa in kept]


def fit_file_score(profile: CellProfile, seed: int, recordings: Sequence[Recording],
                   full_at: Sequence[str | float | None],
                   progress: Callable[[str, str, int], None] | None = None) -> FitFileScore:
    """``profile``'s :data:`PICK_ESTIMATOR` on ``recordings`` (DESIGN §7's defaults): the fit
    recordings :func:`scored_recordings` keeps, chosen once for every candidate."""
    from service.estimators.registry import create
    from service.evaluation.run import evaluate_recordings

    runs = evaluate_recordings(recordings, profile, [create(PICK_ESTIMATOR)], full_at=full_at, progress=progress)
    rmse = [s.soc_rmse_after_600s_pct for ev in runs for s in ev.scores if s.soc_rmse_after_600s_pct is not None]
    return FitFileScore(seed, statistics.fmean(rmse) if rmse else None, len(rmse))


def pick_profile(candidates: Sequence[tuple[CellProfile, FitFileScore]]) -> tuple[CellProfile, FitFileScore]:
    """The candidate with the lowest fit-file SOC RMSE; the first where none could be scored, and the
    first of equals."""
    if not candidates:
        raise ValueError("no candidate profile to pick from")
    scored = [c for c in candidates if c[1].soc_rmse_after_600s_pct is not None]
    if not scored:
        return candidates[0]
    return min(scored, key=lambda c: c[1].soc_rmse_after_600s_pct)  # type: ignore[arg-type, return-value]


def reference_two_rc_variant(profile: CellProfile) -> CellProfile | None:
    """``profile`` with the point at its reference temperature (the fit's: nearest 25 °C) set to its
    textbook 2-RC point, without hysteresis (:func:`~service.characterisation.two_rc_profile.with_two_rc_points`);
    ``None`` where the profile stores no 2-RC fit there, or that point already is the 2-RC point."""
    from service.characterisation.characterise import reference_temperature
    from service.characterisation.two_rc_profile import SAME_TEMP_C, with_two_rc_points

    if profile.ecm2rc is None:
        return None
    ref = reference_temperature(p.temp_c for p in profile.parameters)
    if not any(abs(e.temp_c - ref) < SAME_TEMP_C for e in profile.ecm2rc.points):
        return None
    variant = with_two_rc_points(profile, [ref])
    same = variant.parameters == profile.parameters and variant.hysteresis == profile.hysteresis
    return None if same else variant


def describe_reference_two_rc(kept: FitFileScore, variant: FitFileScore, ref_temp_c: float, written: bool) -> str:
    """The pick's second line: the kept profile read with its reference point the 2-RC point, and
    whether that point is ``written`` (:func:`pick_profile` decides it, as between the seeds)."""
    if variant.soc_rmse_after_600s_pct is None:
        return (f"seed {kept.seed}'s profile with its {ref_temp_c:g} °C point the textbook 2-RC point could not be "
                "scored; keeping the fitted point")
    return (f"seed {kept.seed}'s profile with its {ref_temp_c:g} °C point the textbook 2-RC point (no hysteresis) "
            f"reads {variant.soc_rmse_after_600s_pct:.2f} %; "
            + ("writing that point" if written else "keeping the fitted point"))


def describe_pick(scores: Sequence[FitFileScore], kept: FitFileScore) -> str:
    """What the pick read and kept (the fit log gives it after :data:`PICK_LOG_PREFIX`): each seed's
    fit-file reading and which profile was kept."""
    if kept.soc_rmse_after_600s_pct is None:
        return (f"no fit recording other than an OCV test lasts 600 s past its start, so none "
                f"scores the {len(scores)} candidates; keeping seed {kept.seed}'s")
    read = ", ".join(f"seed {s.seed} {s.soc_rmse_after_600s_pct:.2f} %" if s.soc_rmse_after_600s_pct is not None
                     else f"seed {s.seed} unscored" for s in scores)
    return (f"{PICK_ESTIMATOR}'s SOC RMSE after 600 s on the {kept.recordings_scored} fit "
            f"recording(s) other than OCV tests, from a 20 % wrong start: {read}; keeping seed {kept.seed}'s")
