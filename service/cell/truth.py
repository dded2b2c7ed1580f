"""Truth SOC of a recording: ``soc_true`` if recorded, else coulomb counting from a known
full-charge point with the characterised capacity.  ``socd evaluate`` scores against it
(DESIGN §7); ``socd fit`` characterises the cell along it."""

from __future__ import annotations

import numpy as np

from service.cell.coulomb import coulomb_soc
from service.errors import UserError
from service.recording import Recording
from service.validation import HELD_CURRENT_A


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


def _large_steps(rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    """The current's and the voltage's moves over the current's steps by :data:`SIGN_STEP_SHARE` of its
    largest value or more."""
    d_i, d_v = np.diff(rec.current_a), np.diff(rec.voltage_v)
    peak = float(np.max(np.abs(rec.current_a))) if len(rec) else 0.0
    steps = np.abs(d_i) > SIGN_STEP_SHARE * peak if peak > 0.0 else np.zeros(d_i.size, dtype=bool)
    return d_i[steps], d_v[steps]


def current_sign_steps(rec: Recording) -> tuple[int, int]:
    """``(up, steps)``: of the current's steps by :data:`SIGN_STEP_SHARE` of its largest value or more,
    how many move the voltage the same way. A cell's ohmic drop moves it the other way in socd's
    convention (discharge positive)."""
    d_i, d_v = _large_steps(rec)
    return int(np.count_nonzero(d_v / d_i > 0.0)), int(d_i.size)


def check_voltage_moves(rec: Recording) -> None:
    """Raise :class:`UserError` where the voltage stays exactly where it was at every one of
    :data:`SIGN_MIN_STEPS` or more large current steps (:func:`current_sign_steps`): a stuck channel or a
    constant column, whose voltage no model of the cell can follow (a diagnosis named capacity on it)."""
    d_i, d_v = _large_steps(rec)
    if d_i.size >= SIGN_MIN_STEPS and not np.any(d_v):
        raise UserError(f"{rec.path}: the voltage does not move at any of its {d_i.size} large current steps: "
                        "voltage_v looks stuck or filled with a constant")


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


#: a sample counts as settled light load at or under this share of the recording's largest current
#: (by the current alone: the capacity it would be a C-rate of is what is being checked) ...
LIGHT_LOAD_SHARE = 0.1
#: ... after this long at light load
LIGHT_LOAD_SETTLE_S = 30.0
#: how much of the settled light-load voltage's range is not read as SOC, half at each end
#: (the polarisation left after a pulse, hysteresis, the OCV's temperature dependence)
CAPACITY_SLIP_ALLOWANCE_V = 0.2
#: the SOC span counted with the capacity given, times this, is the most the cell may have moved:
#: a capacity off by less than this factor is the diagnosis's ``capacity`` effect, not a slip
CAPACITY_SLIP_FACTOR = 3.0
#: and the voltage must read at least this span of SOC: on 10 to 30 min windows of every shared real
#: recording, with the right capacity, it read at most 0.30 (a -20 °C pulse test's relaxation); an OCV
#: table fitted without an OCV test can still read more where it is flat and wrong
CAPACITY_SLIP_MIN_SPAN = 0.4


def settled_light_load(rec: Recording) -> np.ndarray:
    """Samples at light load (:data:`LIGHT_LOAD_SHARE` of the largest current) for at least
    :data:`LIGHT_LOAD_SETTLE_S` since the last heavier one."""
    light = np.abs(rec.current_a) <= LIGHT_LOAD_SHARE * float(np.max(np.abs(rec.current_a)))
    last_heavy = np.maximum.accumulate(np.where(light, -1, np.arange(light.size)))
    since = np.where(last_heavy >= 0, rec.time_s - rec.time_s[np.maximum(last_heavy, 0)], np.inf)
    return light & (since >= LIGHT_LOAD_SETTLE_S)


def capacity_slip(rec: Recording, table, capacity_ah: float, source: str) -> str | None:
    """Why ``capacity_ah`` looks many times too large for ``rec``, or None: the settled light-load
    voltage (:func:`settled_light_load`), read on the OCV ``table`` with
    :data:`CAPACITY_SLIP_ALLOWANCE_V` taken off its range, spans at least
    :data:`CAPACITY_SLIP_MIN_SPAN` of SOC and more than :data:`CAPACITY_SLIP_FACTOR` times what the
    charge counted with ``capacity_ah`` moves. A capacity given ten or a hundred times too large reads a
    drive as a few per cent of SOC or less, and a diagnosis names whatever absorbs the voltage it cannot
    explain. A flat OCV (LFP) rarely shows it. Too small a capacity is :func:`check_counted_span`'s."""
    if len(rec) < 2:
        return None
    counted = coulomb_soc(rec.time_s, rec.current_a, capacity_ah, 0.0)
    span = float(np.max(counted) - np.min(counted))
    settled = settled_light_load(rec)
    if np.count_nonzero(settled) < 10:
        return None
    lo, hi = np.percentile(rec.voltage_v[settled], [1.0, 99.0])
    if hi - lo <= CAPACITY_SLIP_ALLOWANCE_V:
        return None
    ends = np.array([lo, hi]) + np.array([1.0, -1.0]) * CAPACITY_SLIP_ALLOWANCE_V / 2
    soc_lo, soc_hi = table.soc_from_ocv(ends, float(np.median(rec.temperature_c)))
    read = float(soc_hi - soc_lo)
    if read < max(CAPACITY_SLIP_FACTOR * span, CAPACITY_SLIP_MIN_SPAN):
        return None
    return (f"{rec.path}: its voltage at rest or light load reads the OCV table across {read:.2f} of the cell or more "
            f"({1e3 * lo:.0f}-{1e3 * hi:.0f} mV), but the charge counted with {source} {capacity_ah:g} Ah moves the SOC "
            f"across only {span:.3f}: the capacity looks {read / max(span, 1e-9):.0f} times too large for this "
            "recording (is it in the right unit?), or the OCV table is far off the cell where it reads")


def ocv_range_problem(rec: Recording, table, source: str) -> str | None:
    """Why the settled light-load voltage of ``rec`` (:func:`settled_light_load`) cannot be read on the
    OCV ``table`` (``source`` names where it came from, e.g. ``the OCV table ocv.csv``), or None: its 99th percentile lies more than half of
    :data:`CAPACITY_SLIP_ALLOWANCE_V` above the table's OCV at SOC 1 (median temperature), a SOC past
    full no cell rests at. A table of another cell or chemistry reads such a voltage as a SOC clipped to 1,
    and a diagnosis names whatever absorbs the hundreds of mV left. On every shared recording with its
    table or bundled profile the voltage stays within 25 mV of it. The bottom is not checked: a cell
    relaxing after a cold cut-off stays 200 mV below the bundled Panasonic profile's OCV at SOC 0."""
    if len(rec) < 2:
        return None
    settled = settled_light_load(rec)
    if np.count_nonzero(settled) < 10:
        return None
    hi = float(np.percentile(rec.voltage_v[settled], 99.0))
    full = float(table.ocv(np.array(1.0), float(np.median(rec.temperature_c))))
    if hi <= full + CAPACITY_SLIP_ALLOWANCE_V / 2:
        return None
    return (f"{rec.path}: its voltage at rest or light load reaches {1e3 * hi:.0f} mV, {1e3 * (hi - full):.0f} mV "
            f"above the OCV at full charge ({1e3 * full:.0f} mV) of {source}: that OCV is not "
            "this cell's (another cell's or chemistry's table?)")


def check_ocv_range(rec: Recording, table, source: str) -> None:
    """Raise :class:`UserError` where :func:`ocv_range_problem` finds the recording outside the table."""
    if (why := ocv_range_problem(rec, table, source)) is not None:
        raise UserError(why)


#: s: a step between samples at least this long, and ...
UNLOGGED_MIN_STEP_S = 60.0
#: ... this many times the recording's median step, is a pause in the logging
UNLOGGED_STEP_FACTOR = 10.0
#: a pause that begins under load, over which the held current counts more than this share of the
#: capacity, with the current not the same on both sides, is refused: the charge that flowed while
#: nothing was logged is not known
UNLOGGED_MAX_SHARE = 0.01
#: the current on both sides of a pause within this share of the larger (plus
#: :data:`HELD_CURRENT_A`) is one constant-current stretch logged sparsely (a C/20 OCV test), not a gap,
#: where the stretch is logged sparsely beside the pause too: a step next to it at least
#: 1/:data:`UNLOGGED_STEP_FACTOR` of its length
CONSTANT_CURRENT_SHARE = 0.05


def unlogged_charge(rec: Recording, capacity_ah: float, source: str) -> str | None:
    """Why ``rec`` has a pause in its logging whose charge is not known, or None.

    Each sample's current is held over the interval before it (:func:`coulomb_soc`).  Over a
    pause (:data:`UNLOGGED_MIN_STEP_S`, :data:`UNLOGGED_STEP_FACTOR`) that begins under load and
    where the current differs on its two sides, or where it is the same but the samples beside the
    pause are logged densely (rows cut out of one constant-current stretch), that counts the resumed
    current over the whole pause (a pause that begins at rest is a logger's sparse logging there, and
    one amid steps as long in a constant-current stretch too); where it counts more than
    :data:`UNLOGGED_MAX_SHARE` of ``capacity_ah``, the truth and every filter's current integral
    after it are off by an amount no sample shows."""
    if len(rec) < 3:
        return None
    step = np.diff(rec.time_s)
    before, after = rec.current_a[:-1], rec.current_a[1:]
    paused = step >= np.maximum(UNLOGGED_MIN_STEP_S, UNLOGGED_STEP_FACTOR * float(np.median(step)))
    changed = np.abs(after - before) > (CONSTANT_CURRENT_SHARE * np.maximum(np.abs(after), np.abs(before))
                                        + HELD_CURRENT_A)
    counted_ah = np.abs(after) * step / 3600.0
    # a logger that logs sparsely at rest pauses with no current before it (a pulse test's rests): the
    # pulse that ends such a pause is held over it, by the logger's timing, not a loss of data
    loaded = np.abs(before) > HELD_CURRENT_A
    # the longer step beside each one (0 at the ends): a constant-current stretch logged sparsely has
    # steps as long around its pauses; one long step amid dense samples is rows that were lost
    beside = np.maximum(np.r_[0.0, step[:-1]], np.r_[step[1:], 0.0])
    sparse = beside * UNLOGGED_STEP_FACTOR >= step
    bad = paused & loaded & (changed | ~sparse) & (counted_ah > UNLOGGED_MAX_SHARE * capacity_ah)
    if not bad.any():
        return None
    k = int(np.argmax(bad))
    how = (f"while the current changes from {before[k]:g} to {after[k]:g} A" if changed[k]
           else f"under {after[k]:g} A, amid samples {beside[k]:g} s apart")
    return (f"{rec.path}: time_s jumps by {step[k]:g} s after {rec.time_s[k]:.10g} s {how}: "
            f"holding {after[k]:g} A over that pause counts {counted_ah[k]:.3g} Ah "
            f"({100 * counted_ah[k] / capacity_ah:.2g} % of {source} {capacity_ah:g} Ah) that no sample saw, "
            "and the charge that did flow is not known: split the recording there")


def check_unlogged_charge(rec: Recording, capacity_ah: float, source: str = "the capacity") -> None:
    """Raise :class:`UserError` where :func:`unlogged_charge` finds a pause whose charge is not known."""
    if (why := unlogged_charge(rec, capacity_ah, source)) is not None:
        raise UserError(why)


def truth_and_start(rec: Recording, capacity_ah: float, full_at: str | float | None) -> tuple[Recording, np.ndarray]:
    """The part of ``rec`` to score and its truth SOC.

    ``full_at``: seconds of the full-charge point, ``"auto"`` to detect the end of the
    CC-CV charge, or ``None`` (the file's start; with ``soc_true`` the recorded truth).
    """
    check_current_sign(rec)
    check_unlogged_charge(rec, capacity_ah)
    if full_at is None:
        start = 0
    elif full_at == "auto":
        start = find_full_charge(rec)
    else:
        t = float(full_at)
        if not rec.time_s[0] <= t <= rec.time_s[-1]:
            raise UserError(f"{rec.path}: --full-at {t:.10g} s is outside the recording "
                            f"({rec.time_s[0]:.10g}..{rec.time_s[-1]:.10g} s)")
        start = int(np.searchsorted(rec.time_s, t))
    part = rec.slice(start)
    if part.soc_true is not None:
        return part, part.soc_true
    return part, coulomb_soc(part.time_s, part.current_a, capacity_ah, 1.0)
