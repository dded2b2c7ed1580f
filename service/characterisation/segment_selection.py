"""Which fit segments a characterisation keeps when a recording holds more samples than it fits.

Both fits (the fractional one, :mod:`service.characterisation.characterise`, and the textbook
2-RC one, :mod:`service.characterisation.ecm2rc_fit`) simulate whole segments, each starting
relaxed at a known SOC, and cap the samples they simulate.  A pulse test repeats the same
few segments at every SOC level (HPPC: a pulse of each amplitude, then the discharge to the
next level), so keeping every k-th segment aliases with that period: when k is a multiple of
it, only one kind survives.  On the Panasonic −20 °C HPPC test (four segment kinds, a stride
of four) the fit then saw nothing but the 1.5 A pulses, and its parameters could not follow
the larger pulses or a sustained load.

:func:`select_segments` therefore groups the segments into kinds (peak current to a quarter
octave, duration to an octave) and takes them in turn from every kind, each kind's segments
in an order that spreads any prefix of them over the kind's SOC range (van der Corput), each
kind starting at a different phase so their first segments lie at different SOCs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TypeVar

import numpy as np

from service.cell.fitting import FitSegment

Segment = TypeVar("Segment", bound=FitSegment)


def segment_kind(seg: FitSegment) -> tuple[int, int]:
    """``(peak-current bin, duration bin)``: ``round(2·log2 |I|max)`` (a pulse test's amplitudes,
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


#: each kind's spread order starts this far (mod 1) past the previous kind's, so the kinds'
#: first segments lie at different SOCs (the golden ratio's fraction never repeats a phase)
KIND_PHASE = (math.sqrt(5.0) - 1.0) / 2.0


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
    """Whole segments within ``budget`` samples, every kind of segment represented.

    All of them when they fit.  Otherwise the kinds (:func:`segment_kind`) take turns, in the
    order each first appears, each giving its next segment in :func:`spread_order` (started at
    a different phase per kind); a segment
    that would overrun the budget is passed over for smaller ones.  The kept segments come back
    in recording order; at least one is kept."""
    total = sum(len(s) for s in segs)
    if total <= budget:
        return list(segs)
    kinds: dict[tuple[int, int], list[int]] = {}
    for i, s in enumerate(segs):
        kinds.setdefault(segment_kind(s), []).append(i)
    queues = [[members[j] for j in spread_order(len(members), (k * KIND_PHASE) % 1.0)]
              for k, members in enumerate(kinds.values())]
    keep: list[int] = []
    used = 0
    while any(queues):
        for q in queues:
            if not q:
                continue
            i = q.pop(0)
            if used + len(segs[i]) <= budget:
                keep.append(i)
                used += len(segs[i])
    if not keep:
        keep = [min(range(len(segs)), key=lambda i: len(segs[i]))]
    return [segs[i] for i in sorted(keep)]
