"""The scoring protocol of DESIGN §7 as a library: estimators run on recordings and scored.

Per recording: the part from the full-charge point on is scored against its truth SOC
(:func:`service.cell.truth.truth_and_start`); every estimator starts there with the SOC wrong
by ``init_soc_error`` (:func:`wrong_start`), optionally warm (its polarisation states driven by
the current recorded before the start) and optionally reading a current with a sensor offset
the truth does not contain.  ``socd evaluate`` and the research tools both call
:func:`evaluate_recordings`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np

from service.cell.profile import CellProfile
from service.cell.truth import check_counted_truth, truth_and_start
from service.estimators.base import EstimateTrace, Estimator
from service.evaluation.metrics import Scores, score
from service.recording import Recording

#: called before each estimator runs: (recording name, estimator name, samples scored)
Progress = Callable[[str, str, int], None]


@dataclass
class EstimatorScore(Scores):
    """One estimator's scores on one recording (the rows of ``socd evaluate``'s table and JSON)."""

    recording: str
    estimator: str
    us_per_step: float


@dataclass
class RecordingEvaluation:
    """Every estimator run on one recording: the scored part, its truth, traces and scores."""

    recording: Recording
    part: Recording
    truth: np.ndarray
    traces: dict[str, EstimateTrace]
    scores: list[EstimatorScore]


def wrong_start(truth0: float, error: float) -> float:
    """Initial SOC off by ``error``: added, or subtracted where truth starts above 0.8."""
    return truth0 - error if truth0 > 0.8 else truth0 + error


def scored_truth(rec: Recording, capacity_ah: float, full_at: str | float | None) -> tuple[Recording, np.ndarray]:
    """The part of ``rec`` scored and its truth SOC (:func:`truth_and_start`), a counted truth checked."""
    part, truth = truth_and_start(rec, capacity_ah, full_at)
    if part.soc_true is None:
        check_counted_truth(part, truth, capacity_ah)
    return part, truth


def evaluate_recordings(
    recordings: Sequence[Recording],
    profile: CellProfile,
    estimators: Sequence[Estimator],
    full_at: Sequence[str | float | None] | None = None,
    init_soc_error: float = 0.20,
    warm_start: bool = False,
    current_bias_c: float = 0.0,
    progress: Progress | None = None,
) -> Iterator[RecordingEvaluation]:
    """Run every estimator on every recording and score it, one recording at a time.

    ``full_at``: per recording, the full-charge point as :func:`truth_and_start` takes it
    (default: every file's start).  ``current_bias_c``: a current-sensor offset in units of
    1C added to the current the estimators read (the truth keeps the recorded current).
    A generator, so a caller can write each recording's traces before the next one runs; every
    recording's truth is worked out (and refused, if it cannot be) before the first one runs, so a
    bad file late in the list leaves no output of the files before it.
    """
    full = list(full_at) if full_at is not None else [None] * len(recordings)
    if len(full) != len(recordings):
        raise ValueError(f"{len(full)} full-charge points for {len(recordings)} recordings")
    capacity = profile.effective_capacity_ah
    truths = [scored_truth(rec, capacity, fa) for rec, fa in zip(recordings, full)]
    for rec, (part, truth) in zip(recordings, truths):
        soc0 = wrong_start(float(truth[0]), init_soc_error)
        # the samples up to the start: the start sample's own interval is spent here, and
        # the scored part's first step has dt = 0 (Recording.dt_s), so nothing is counted twice
        history = rec.slice(0, len(rec) - len(part) + 1) if warm_start and len(part) < len(rec) else None
        if current_bias_c:
            bias_a = current_bias_c * capacity
            part_seen = replace(part, current_a=part.current_a + bias_a)
            history = None if history is None else replace(history, current_a=history.current_a + bias_a)
        else:
            part_seen = part
        traces: dict[str, EstimateTrace] = {}
        scores: list[EstimatorScore] = []
        for est in estimators:
            if progress is not None:
                progress(rec.name, est.name, len(part))
            t0 = time.perf_counter()
            trace = est.run(part_seen, profile, soc0, history=history)
            us = 1e6 * (time.perf_counter() - t0) / len(part)
            traces[est.name] = trace
            s = score(part.time_s, trace.soc, truth, trace.v_pred, part.voltage_v, trace.soc_std)
            scores.append(EstimatorScore(recording=rec.name, estimator=est.name, us_per_step=us, **asdict(s)))
        yield RecordingEvaluation(recording=rec, part=part, truth=truth, traces=traces, scores=scores)
