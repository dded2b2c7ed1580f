"""What one ``socd fit`` run found, as a file a script can read (``socd fit --report``): each
candidate's figures per temperature with the quality check's verdict on them, its fit-file SOC
reading where the pick ran, and which candidate the profile is.

The log says the same for a person; this is the form to read it by machine (the fit-quality table
of docs/results/characterisation.md is built from it), so no one parses the log's wording.
"""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import BaseModel, Field

from service.characterisation.characterise import TemperatureFit, reference_temperature

#: a temperature's ``source`` where the profile pick wrote the stored 2-RC point over the fitted one
PICKED_TWO_RC_SOURCE = "2-RC point (profile pick)"


class TemperatureSummary(BaseModel):
    """One temperature's fit (:class:`~service.characterisation.characterise.TemperatureFit`) and the
    quality check's verdict on it."""

    temp_c: float
    #: the fractional model's RMSE over the temperature's segments, mV
    rmse_mv: float | None
    #: the textbook 2-RC model's RMSE in its own fit, and simulated as the fractional model is, mV
    ecm_rmse_mv: float | None
    ecm_simulated_mv: float | None
    #: RMS of the measured voltage minus the OCV at the counted SOC, mV: what the dynamics explain
    overpotential_rms_mv: float
    #: ``rmse_mv / overpotential_rms_mv``: 0 explains every millivolt, 1 none
    unexplained_share: float | None
    #: which point the profile keeps there: "fractional fit", "2-RC start" or "2-RC fit" from the fit,
    #: or :data:`PICKED_TWO_RC_SOURCE` where the profile pick wrote the 2-RC point at the reference
    #: temperature (``rmse_mv``, ``unexplained_share`` and ``at_bounds`` then still describe the
    #: fractional fit the pick read it against)
    source: str
    #: search coordinates that ended on a bound, e.g. "i0_a = 0.05 (lower bound)"
    at_bounds: list[str]
    ocv_measured: bool
    #: why the quality check refuses this temperature (``None``: it passes)
    problem: str | None
    #: the kept point's RMSE over every segment, mV, where the search saw a subsample of them
    #: (``None``: it saw them all, and ``rmse_mv`` is that figure)
    whole_rmse_mv: float | None = None

    @classmethod
    def of(cls, fit: TemperatureFit) -> TemperatureSummary:
        return cls(temp_c=fit.temp_c, rmse_mv=_finite(fit.rmse_mv), ecm_rmse_mv=_finite(fit.ecm_rmse_mv),
                   ecm_simulated_mv=_finite(fit.ecm_simulated_mv),
                   overpotential_rms_mv=fit.overpotential_rms_mv, unexplained_share=_finite(fit.unexplained_share),
                   source=fit.source, at_bounds=list(fit.at_bounds), ocv_measured=fit.ocv_measured,
                   problem=fit.problem(), whole_rmse_mv=_finite(fit.whole_rmse_mv))


def with_picked_two_rc(temperatures: list[TemperatureSummary]) -> list[TemperatureSummary]:
    """``temperatures`` with the reference temperature's ``source`` saying the profile pick wrote the
    2-RC point there (:func:`service.characterisation.profile_pick.reference_two_rc_variant`)."""
    if not temperatures:
        return temperatures
    ref = reference_temperature(t.temp_c for t in temperatures)
    return [t.model_copy(update={"source": PICKED_TWO_RC_SOURCE}) if t.temp_c == ref else t for t in temperatures]


class CandidateSummary(BaseModel):
    """One candidate profile (``socd fit --candidates``): its optimiser seed, figures and verdict."""

    seed: int
    #: this candidate is the profile written
    written: bool
    #: the quality check's refusal (``None`` where it passes, or where ``--force`` wrote it anyway)
    refusal: str | None
    #: the pick's reading: ``fomiukf``'s mean SOC RMSE after 600 s on the fit recordings, %
    #: (``None`` where the pick did not run or could not score it)
    fit_file_soc_rmse_after_600s_pct: float | None = None
    #: the written candidate read the same way with its reference temperature's point the textbook 2-RC
    #: point (``None`` for the others, or where the pick did not read it), and whether that point was written
    reference_two_rc_soc_rmse_after_600s_pct: float | None = None
    reference_two_rc_written: bool = False
    temperatures: list[TemperatureSummary]
    #: the candidate's fit log, line by line (without the ``[fit]`` prefix)
    log: list[str]


class FitSummary(BaseModel):
    """The whole run: the profile written and every candidate fitted for it."""

    profile: str
    #: the pick's account (the profile's ``notes.profile_pick``); ``None`` with one candidate
    profile_pick: str | None
    candidates: list[CandidateSummary] = Field(min_length=1)

    def written(self) -> CandidateSummary:
        """The candidate the profile is."""
        return next(c for c in self.candidates if c.written)

    def save(self, path: Path) -> None:
        path.write_text(self.model_dump_json(indent=2) + "\n", encoding="utf-8")

    @classmethod
    def load(cls, path: Path) -> FitSummary:
        return cls.model_validate_json(Path(path).read_text(encoding="utf-8"))


def _finite(x: float | None) -> float | None:
    """JSON has no NaN: a fit that produced none is ``None``."""
    return None if x is None or not math.isfinite(x) else float(x)
