"""Recordings sampled faster than the fit's period, block-averaged to it before ``socd fit``.

The fractional model's G-L sum (Zeng Eq. 2) is cut after ``L`` samples, so the memory a fit gives
its CPE branches is ``L`` times the fit data's sample period: 16 s at 1 s samples, 1.6 s at 10 Hz.
Fitted at 10 Hz, the branches are fitted as other branches, and the profile generalises worse to
other drives and temperatures than one fitted on the same data's 1 s block averages
(``sample_period`` in docs/results/characterisation.md).  The estimators keep the fitted memory's
span at any rate they run at (:mod:`service.cell.memory`), so a profile fitted on 1 s averages runs
on a 10 Hz bus with a 16 s memory.

A block is ``[t0 + k·P, t0 + (k+1)·P)`` from the recording's first sample ``t0``; its mean of every
column is stamped at the block's start, as the Panasonic 18650PF recordings were shared (1 s block
averages of their 10 Hz logs).  Blocks without a sample (a gap in the log) are left out, so a gap
stays a gap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.cell.memory import sample_period_s
from service.recording import Recording

#: the fit's sample period by default, s: the rate the defaults were chosen at
DEFAULT_FIT_PERIOD_S = 1.0
#: the longest block, s: longer ones would average away the 1-100 s dynamics the model is fitted to
MAX_FIT_PERIOD_S = 10.0
#: a recording is averaged when its sample period is below this share of the fit's period
FASTER_THAN = 0.9


@dataclass(frozen=True)
class Averaged:
    """What :func:`to_fit_period` did to one recording."""

    recording: Recording
    period_s: float | None  # the recording's own sample period (None: fewer than two samples)
    averaged: bool


def block_average(rec: Recording, period_s: float) -> Recording:
    """``rec`` as means over blocks of ``period_s`` seconds, stamped at each block's start."""
    if not period_s > 0:
        raise ValueError(f"block period must be > 0 s, got {period_s}")
    t0 = float(rec.time_s[0])
    block = np.floor((rec.time_s - t0) / period_s + 1e-9).astype(np.int64)
    keys, index, counts = np.unique(block, return_inverse=True, return_counts=True)

    def mean(x: np.ndarray) -> np.ndarray:
        return np.bincount(index, weights=x, minlength=keys.size) / counts

    return Recording(
        path=rec.path,
        time_s=t0 + keys * period_s,
        current_a=mean(rec.current_a),
        voltage_v=mean(rec.voltage_v),
        temperature_c=mean(rec.temperature_c),
        soc_true=None if rec.soc_true is None else mean(rec.soc_true),
    )


def to_fit_period(recordings: list[Recording], period_s: float) -> list[Averaged]:
    """Each recording block-averaged to ``period_s`` where it is sampled faster (``period_s`` 0:
    every recording as it is)."""
    out: list[Averaged] = []
    for rec in recordings:
        own = sample_period_s(rec.time_s)
        faster = period_s > 0 and own is not None and own < FASTER_THAN * period_s
        out.append(Averaged(block_average(rec, period_s) if faster else rec, own, faster))
    return out


def describe(averaged: list[Averaged], period_s: float) -> str | None:
    """One line for the fit log naming the recordings that were averaged, or None."""
    done = [a for a in averaged if a.averaged]
    if not done:
        return None
    names = ", ".join(f"{a.recording.name} ({a.period_s:.3g} s)" for a in done)
    return (f"sample period: {names} block-averaged to {period_s:g} s before the fit, so the G-L memory spans "
            f"the same time as at the defaults' rate (--fit-period 0 fits at the recorded rate)")
