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


#: a current step counts towards the sign test when it moves by this share of the largest current
SIGN_STEP_SHARE = 0.2
#: steps the sign test needs before it says anything
SIGN_MIN_STEPS = 20
#: the share of those steps whose voltage moves with the current that says charge is logged positive:
#: on every shared, labelled, development and PyBaMM recording it is at most 0.07 on a drive and about
#: 0.5 on a C/20 OCV test (its steps are sensor noise); a drive with its current negated reads 0.94 or more
SIGN_AGREEMENT = 0.8


def current_sign_steps(rec: Recording) -> tuple[int, int]:
    """``(up, steps)``: of the current's steps by :data:`SIGN_STEP_SHARE` of its largest value or more,
    how many move the voltage the same way. A cell's ohmic drop moves it the other way in socd's
    convention (discharge positive)."""
    d_i, d_v = np.diff(rec.current_a), np.diff(rec.voltage_v)
    peak = float(np.max(np.abs(rec.current_a))) if len(rec) else 0.0
    steps = np.abs(d_i) > SIGN_STEP_SHARE * peak if peak > 0.0 else np.zeros(d_i.size, dtype=bool)
    return int(np.count_nonzero(d_v[steps] / d_i[steps] > 0.0)), int(np.count_nonzero(steps))


def check_current_sign(rec: Recording) -> None:
    """Raise :class:`UserError` where the voltage moves with the current at more than
    :data:`SIGN_AGREEMENT` of :data:`SIGN_MIN_STEPS` or more large steps: the current was logged with
    charge positive, and every count, fit and estimate on it would run the wrong way."""
    up, steps = current_sign_steps(rec)
    if steps >= SIGN_MIN_STEPS and up > SIGN_AGREEMENT * steps:
        raise UserError(f"{rec.path}: the voltage jumps up where the current steps up at {up} of its {steps} large "
                        "current steps: charge looks logged positive, and socd counts discharge positive (negate "
                        "current_a)")


#: a recording whose largest current is under this C-rate of the capacity given has nothing to diagnose
#: with; every drive, pulse test and C/20 OCV test passes it, a capacity in mAh does not (a parked
#: log can be scored, so ``socd evaluate`` does not ask it; ``socd fit`` refuses such a file for its
#: lack of current steps and gives the C-rate)
MIN_PEAK_C = 0.02


def check_current_scale(rec: Recording, capacity_ah: float, source: str) -> None:
    """Raise :class:`UserError` where the current never reaches :data:`MIN_PEAK_C` of ``capacity_ah``
    (``source`` names where that capacity came from, e.g. ``--capacity-ah``): a capacity given in mAh
    reads every current as a thousandth of its C-rate, and the diagnosis would see a cell at rest."""
    peak = float(np.max(np.abs(rec.current_a))) if len(rec) else 0.0
    if peak < MIN_PEAK_C * capacity_ah:
        raise UserError(f"{rec.path}: its largest current is {peak:.3g} A, {peak / capacity_ah:.2g}C of "
                        f"{source} {capacity_ah:g}: nothing to estimate with at under {MIN_PEAK_C:g}C "
                        "(is the capacity in mAh?)")


def count_hint(rec: Recording) -> str:
    """The span and sample step the time column gives, for a refusal of a charge count that left
    [0, 1] (a time in ms reads a thousand times too long)."""
    if len(rec) < 2:
        return ""
    span_h = float(rec.time_s[-1] - rec.time_s[0]) / 3600.0
    return f" (it spans {span_h:.3g} h at a median step of {float(np.median(np.diff(rec.time_s))):.3g} s)"


def check_counted_truth(rec: Recording, truth: np.ndarray, capacity_ah: float) -> None:
    """Raise :class:`UserError` where a truth counted with ``capacity_ah`` leaves [0, 1] by more than
    :data:`COUNTED_SOC_MARGIN`: every score against it would be meaningless (a current in mA reads
    as a thousand times the charge)."""
    if (where := counted_soc_excursion(truth)) is not None:
        raise UserError(f"{rec.path}: the truth SOC counted from the full-charge point with {capacity_ah:g} Ah "
                        f"reaches {where}: the current's unit, the capacity or the full-charge point (--full-at) "
                        f"is wrong for this recording{count_hint(rec)}")


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
                        f"or the capacity is wrong for this recording{count_hint(rec)}")


def truth_and_start(rec: Recording, capacity_ah: float, full_at: str | float | None) -> tuple[Recording, np.ndarray]:
    """The part of ``rec`` to score and its truth SOC.

    ``full_at``: seconds of the full-charge point, ``"auto"`` to detect the end of the
    CC-CV charge, or ``None`` (the file's start; with ``soc_true`` the recorded truth).
    """
    check_current_sign(rec)
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
