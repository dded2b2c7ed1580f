"""Per-estimator summary of a scored set of recordings (DESIGN §7): mean and worst SOC RMSE after
the first 600 s, on how many recordings an estimator is below the textbook bar, and how often the
σ it publishes covers its error.

This is the figure a held-out check reads ("mean / worst"), so ``socd evaluate`` prints it under
its table and writes it to its JSON.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from service.evaluation.run import EstimatorScore


@dataclass(frozen=True)
class EstimatorSummary:
    """One estimator over every recording it was scored on."""

    estimator: str
    #: recordings scored (those shorter than 600 s after the start have no RMSE after 600 s)
    recordings: int
    #: recordings with an RMSE after 600 s: what the mean and the worst are taken over
    scored: int
    mean_rmse_after_600s_pct: float | None
    worst_rmse_after_600s_pct: float | None
    worst_recording: str | None
    #: recordings where this estimator's RMSE after 600 s is below the bar's (None for the bar
    #: itself, or when no bar ran); ``compared`` is how many recordings both have a figure on
    below_bar: int | None
    compared: int | None
    #: mean over the recordings of the share of samples after 600 s within twice the σ the estimator
    #: publishes (95 % for an honest σ); None for an estimator without a σ (coulomb counting)
    mean_within_2sigma_pct: float | None = None


def summarise(results: Sequence[EstimatorScore], bar: str | None) -> list[EstimatorSummary]:
    """One :class:`EstimatorSummary` per estimator, in the order they first appear in ``results``."""
    names = list(dict.fromkeys(r.estimator for r in results))
    bar_rmse = {r.recording: r.soc_rmse_after_600s_pct for r in results if r.estimator == bar}
    out = []
    for name in names:
        mine = [r for r in results if r.estimator == name]
        late = [r for r in mine if r.soc_rmse_after_600s_pct is not None]
        worst = max(late, key=lambda r: r.soc_rmse_after_600s_pct, default=None)
        below = compared = None
        if bar in names and name != bar:
            pairs = [(r.soc_rmse_after_600s_pct, bar_rmse[r.recording]) for r in late
                     if bar_rmse.get(r.recording) is not None]
            compared = len(pairs)
            below = sum(a < b for a, b in pairs)
        out.append(EstimatorSummary(
            estimator=name, recordings=len(mine), scored=len(late),
            mean_rmse_after_600s_pct=_mean_or_none([r.soc_rmse_after_600s_pct for r in late]),
            worst_rmse_after_600s_pct=None if worst is None else worst.soc_rmse_after_600s_pct,
            worst_recording=None if worst is None else worst.recording,
            below_bar=below, compared=compared,
            mean_within_2sigma_pct=_mean_or_none([r.soc_within_2sigma_pct for r in late])))
    return out


def _mean_or_none(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return float(np.mean(known)) if known else None


def summary_lines(summaries: Sequence[EstimatorSummary], bar: str | None) -> list[str]:
    """The summary as ``socd evaluate`` prints it under its table."""
    if not summaries:
        return []
    lines = ["SOC RMSE after 600 s, mean / worst over the recordings scored:"]
    width = max(len(s.estimator) for s in summaries)
    for s in summaries:
        if s.mean_rmse_after_600s_pct is None:
            lines.append(f"  {s.estimator:{width}s}  - (no recording runs past 600 s)")
            continue
        line = (f"  {s.estimator:{width}s}  {s.mean_rmse_after_600s_pct:.2f} / {s.worst_rmse_after_600s_pct:.2f} % "
                f"over {s.scored} (worst: {s.worst_recording})")
        if s.below_bar is not None:
            line += f"; below the {bar} bar on {s.below_bar} of {s.compared}"
        if s.mean_within_2sigma_pct is not None:
            line += f"; its σ covers {s.mean_within_2sigma_pct:.0f} % at 2σ"
        lines.append(line)
    return lines
