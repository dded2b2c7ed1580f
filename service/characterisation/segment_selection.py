"""Which fit segments a characterisation keeps when a recording holds more samples than it fits.

Both fits (the fractional one, :mod:`service.characterisation.characterise`, and the textbook
2-RC one, :mod:`service.characterisation.ecm2rc_fit`) simulate whole segments, each starting
relaxed at a known SOC, and cap the samples they simulate.  A pulse test repeats the same
few segments at every SOC level (HPPC: a pulse of each amplitude, then the discharge to the
next level), so keeping every k-th segment aliases with that period: when k is a multiple of
it, only one kind survives.  On the Panasonic −20 °C HPPC test (four segment kinds, a stride
of four) the fit then saw nothing but the 1.5 A pulses, and its parameters could not follow
the larger pulses or a sustained load.

:func:`select_segments` therefore samples by kind (peak current to a quarter octave, length to
an octave), as a stratified sample does: every kind is kept, each in proportion to its share
of the samples, and each kind's segments are spread over its SOC range (van der Corput order,
started at a different phase per kind so their first segments lie at different SOCs).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TypeVar

import numpy as np

from service.cell.fitting import FitSegment

Segment = TypeVar("Segment", bound=FitSegment)

#: each kind's spread order starts this far (mod 1) past the previous kind's (the golden
#: ratio's fraction, which never brings two kinds back to the same phase)
KIND_PHASE = (math.sqrt(5.0) - 1.0) / 2.0


def segment_kind(seg: FitSegment) -> tuple[int, int]:
    """``(peak-current bin, length bin)``: ``round(2·log2 |I|max)`` (a pulse test's amplitudes,
    each about double the last, fall in different bins) and ``round(log2 samples)``."""
    peak = float(np.max(np.abs(seg.current_a))) if len(seg) else 0.0
    return (round(2.0 * math.log2(max(peak, 1e-3))), round(math.log2(max(len(seg), 1))))


def van_der_corput(k: int) -> float:
    """The ``k``-th point of the base-2 van der Corput sequence in [0, 1): 0, ½, ¼, ¾, ⅛, …"""
    out, scale = 0.0, 0.5
    while k:
        out += scale * (k & 1)
        k >>= 1
        scale /= 2
    return out


def spread_order(n: int, phase: float = 0.0) -> list[int]:
    """``0..n-1`` so that every prefix is spread evenly over the range: position
    ``(van der Corput(r) + phase) mod 1`` of the range for ``r`` = 0, 1, …, the next free
    index where that one is taken."""
    order: list[int] = []
    free = [True] * n
    for r in range(n):
        i = int(((van_der_corput(r) + phase) % 1.0) * n)
        while not free[i]:
            i = (i + 1) % n
        free[i] = False
        order.append(i)
    return order


def select_segments(segs: Sequence[Segment], budget: int) -> list[Segment]:
    """Whole segments within ``budget`` samples: a sample stratified by :func:`segment_kind`.

    All of them when they fit.  Otherwise each step takes the next segment (:func:`spread_order`)
    of the kind furthest below its share of the samples kept so far (the share it has of all
    samples; a kind with none kept yet comes first, the largest first), passing over a segment
    that would overrun the budget.  The kept segments come back in recording order; at least
    one (the shortest) is kept."""
    total = sum(len(s) for s in segs)
    if total <= budget:
        return list(segs)
    members: dict[tuple[int, int], list[int]] = {}
    for i, s in enumerate(segs):
        members.setdefault(segment_kind(s), []).append(i)
    # each kind with its samples, largest first
    sized = sorted(((sum(len(segs[i]) for i in m), m) for m in members.values()), key=lambda x: -x[0])
    groups = [m for _, m in sized]
    share = [n / total for n, _ in sized]
    queues = [[m[j] for j in spread_order(len(m), (k * KIND_PHASE) % 1.0)] for k, m in enumerate(groups)]
    kept = [0] * len(groups)
    keep: list[int] = []
    used = 0
    while any(queues):
        k = min((k for k, q in enumerate(queues) if q), key=lambda k: kept[k] / share[k])
        i = queues[k].pop(0)
        if used + len(segs[i]) <= budget:
            keep.append(i)
            used += len(segs[i])
            kept[k] += len(segs[i])
    if not keep:
        keep = [min(range(len(segs)), key=lambda i: len(segs[i]))]
    return [segs[i] for i in sorted(keep)]
