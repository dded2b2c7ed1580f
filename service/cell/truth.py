"""Truth SOC of a recording: ``soc_true`` if recorded, else coulomb counting from a known
full-charge point with the characterised capacity.  ``socd evaluate`` scores against it
(DESIGN §7); ``socd fit`` characterises the cell along it."""

from __future__ import annotations

import numpy as np

from service.cell.coulomb import coulomb_soc
from service.errors import UserError
from service.recording import Recording


def per_recording(values: list[str] | None, n: int, flag: str) -> list[str | None]:
    """A flag given once (applies to all) or once per recording, expanded to ``n`` values."""
    values = values or [None]
    if len(values) not in (1, n):
        raise UserError(f"{flag} given {len(values)} times for {n} recordings: give it once or once per recording")
    return values * n if len(values) == 1 else list(values)


def find_full_charge(rec: Recording) -> int:
    """Index of the end of the last CC-CV charge before the first discharge after it.

    The end of CV is the last charging sample within 10 mV of the recording's maximum
    voltage.  Raises :class:`UserError` if the recording holds no such charge.
    """
    v_top = rec.voltage_v.max() - 0.010
    charging_top = np.flatnonzero((rec.current_a < -0.005) & (rec.voltage_v >= v_top))
    if charging_top.size == 0:
        raise UserError(f"{rec.path}: --full-at auto: no CC-CV charge found (no charging sample near max voltage)")
    # the CV phase ends where it is followed by a non-charging stretch
    first = charging_top[0]
    after = np.flatnonzero(rec.current_a[first:] > 0.05)
    limit = first + (after[0] if after.size else rec.current_a.size - first)
    in_phase = charging_top[charging_top < limit]
    return int(in_phase[-1])


#: how far a charge count may leave [0, 1] (a fraction of the capacity: a capacity a few percent off,
#: a full point a little early); further, the capacity, the current's unit or the full-charge point is
#: wrong for the recording (scored by ``socd evaluate``; refused by ``socd fit``)
COUNTED_SOC_MARGIN = 0.1


def counted_soc_excursion(counted: np.ndarray) -> str | None:
    """The reading (``"-0.35"``) where a charge count leaves [0, 1] by more than
    :data:`COUNTED_SOC_MARGIN`, or None."""
    lo, hi = float(np.min(counted)), float(np.max(counted))
    if lo < -COUNTED_SOC_MARGIN:
        return f"{lo:.2f}"
    return f"{hi:.2f}" if hi > 1.0 + COUNTED_SOC_MARGIN else None


def check_counted_truth(rec: Recording, truth: np.ndarray, capacity_ah: float) -> None:
    """Raise :class:`UserError` where a truth counted with ``capacity_ah`` leaves [0, 1] by more than
    :data:`COUNTED_SOC_MARGIN`: every score against it would be meaningless (a current in mA reads
    as a thousand times the charge)."""
    if (where := counted_soc_excursion(truth)) is not None:
        raise UserError(f"{rec.path}: the truth SOC counted from the full-charge point with {capacity_ah:g} Ah "
                        f"reaches {where}: the current's unit, the capacity or the full-charge point (--full-at) "
                        "is wrong for this recording")


def check_counted_span(rec: Recording, capacity_ah: float) -> None:
    """Raise :class:`UserError` where the charge counted along ``rec`` with ``capacity_ah`` spans more
    than the whole cell (by :data:`COUNTED_SOC_MARGIN`) between its highest and lowest point, whatever
    SOC it started at: the current's unit (mA) or the capacity is wrong. For a recording with no
    full-charge point to count a truth from (``socd diagnose``)."""
    counted = coulomb_soc(rec.time_s, rec.current_a, capacity_ah, 0.0)
    span = float(np.max(counted) - np.min(counted))
    if span > 1.0 + COUNTED_SOC_MARGIN:
        raise UserError(f"{rec.path}: the charge counted with {capacity_ah:g} Ah moves the SOC across "
                        f"{span:.2f} of the cell between its highest and lowest point: the current's unit "
                        "or the capacity is wrong for this recording")


def truth_and_start(rec: Recording, capacity_ah: float, full_at: str | float | None) -> tuple[Recording, np.ndarray]:
    """The part of ``rec`` to score and its truth SOC.

    ``full_at``: seconds of the full-charge point, ``"auto"`` to detect the end of the
    CC-CV charge, or ``None`` (the file's start; with ``soc_true`` the recorded truth).
    """
    if full_at is None:
        start = 0
    elif full_at == "auto":
        start = find_full_charge(rec)
    else:
        t = float(full_at)
        if not rec.time_s[0] <= t <= rec.time_s[-1]:
            raise UserError(f"{rec.path}: --full-at {t:g} s is outside the recording "
                            f"({rec.time_s[0]:g}..{rec.time_s[-1]:g} s)")
        start = int(np.searchsorted(rec.time_s, t))
    part = rec.slice(start)
    if part.soc_true is not None:
        return part, part.soc_true
    return part, coulomb_soc(part.time_s, part.current_a, capacity_ah, 1.0)
