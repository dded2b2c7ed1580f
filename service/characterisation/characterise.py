"""Characterise a cell from recordings whose SOC is known: the engine of ``socd fit``.

1. The textbook 2-RC model per temperature group (:mod:`service.characterisation.ecm2rc_fit`):
   the bar the fractional model must clear, stored in the profile for ``ecm2rc-ekf``.
2. OCV(SOC): an OCV table (``--ocv``), else a slow OCV test among the recordings, both
   aligned to the relaxed voltages at the end of long rests (HPPC tests): first their SOC
   scale, where the rests span enough SOC (:func:`~service.characterisation.ocv_sources.soc_alignment`),
   then a voltage offset; else, at each temperature, the monotone OCV fitted jointly with the 2-RC model
   in step 1 (a linear problem for each pair of time constants, so it cannot diverge).
3. MTS-FOM parameters per temperature group with :func:`service.cell.fitting.fit_parameters`
   (scipy differential evolution, then least squares), started from the 2-RC model's
   point and kept only where they fit better than it (with a jointly fitted OCV, a search
   that ends on the 2-RC submodel keeps the 2-RC fit's point, which belongs with that OCV).  Long tests are cut into segments
   that start at the end of a rest (relaxed branches, SOC known by coulomb counting) so
   pulses are fitted at full time resolution.  A temperature whose fit is poor or worse
   than the 2-RC fit is reported (:func:`check_fit_quality`), and ``socd fit`` refuses it.
4. Optional (``--soc-resistance``): the resistances' dependence on SOC at each temperature,
   measured directly from the HPPC discharge pulses (:mod:`service.cell.soc_dependence`)
   before step 3, so the parameters are fitted with it in the model.
5. Optional (``--slow-branch``): a slow RC branch measured from the voltage recovery in
   long rests at the reference temperature (:mod:`service.characterisation.relaxation`),
   added before step 3, so the CPE branches do not have to imitate it (the 2-RC fit of
   step 1, and a joint OCV from it, are fitted without it).  Fitted segments start with
   it relaxed, as they do the CPE branches.  The branch has no temperature dependence: it
   is used as measured at every temperature.
"""

from __future__ import annotations

import sys
from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np

from service.cell.coulomb import coulomb_soc
from service.cell.current_steps import (
    STEP_MIN_PEAK_C,
    STEP_MIN_STEPS,
    current_steps,
    steps_peak_c,
    steps_resolve_kinetics,
)
from service.cell.fitting import (
    BASE_NAMES,
    LAW_UPDATE_K,
    LINEAR_I0_A,
    FitResult,
    FitSegment,
    encode_point,
    fit_parameters,
    last_current_direction,
)
from service.cell.memory import median_interval_s
from service.cell.ocv import GRID_POINTS, OcvTable, flat_share, make_monotone
from service.cell.profile import (
    BranchSpec,
    CellParameters,
    CellProfile,
    Ecm2RcPoint,
    Ecm2RcSpec,
    Extensions,
    HysteresisSpec,
    OcvSpec,
    ParameterPoint,
    SocResistanceSpec,
    lift_to_ohmic_floor,
)
from service.cell.rests import load_level_a, rest_level_a
from service.cell.soc_dependence import pulse_resistances, scale_rows
from service.cell.temperature_law import scaled_by_law, temperature_law_factor
from service.cell.trajectory import simulate_batch
from service.cell.truth import count_hint, counted_soc_excursion, truth_and_start
from service.characterisation.ecm2rc_fit import TAU1_BOUNDS_S, TAU2_BOUNDS_S, Ecm2RcFit, fit_ecm2rc
from service.characterisation.ocv_choices import (
    DEFAULT_OCV_BETWEEN_RESTS,
    NEAR_REFERENCE_K,
    OCV_SMOOTH_WEIGHT,
    REST_INTERP_MAX_GAP,
)
from service.characterisation.ocv_sources import (
    REST_MIN_S,
    RestPoint,
    alignment_at_bound,
    capacity_above_test,
    interpolate_between_rests,
    is_ocv_test,
    ocv_from_test,
    ocv_row_from_rests,
    ocv_rows_by_temperature,
    rest_alignment,
    rest_points,
    rest_spans,
    rests_settled,
)
from service.characterisation.relaxation import measure_slow_relaxation
from service.characterisation.segment_selection import select_segments
from service.characterisation.shape_choices import DEFAULT_SHAPE, SHAPES
from service.characterisation.sustained_load import (
    SUSTAINED_C_RATE,
    SUSTAINED_S,
    one_point_profile,
    sustained_polarisation_mv,
)
from service.recording import Recording

TEMP_GROUP_C = 5.0
MAX_FIT_SAMPLES = 16000
SEGMENT_REST_S = 300.0
#: a recording cut at a SOC at least this high starts just after a charge (hysteresis branch)
FULL_SOC = 0.98
#: segments starting below this SOC are not fitted: near empty the cell is strongly
#: non-linear and a few samples there would dominate the squared error
MIN_FIT_SOC = 0.1
#: SOC points of the resistance-scale table (--soc-resistance)
SOC_RESISTANCE_POINTS = 21
#: the fractional diffusion branch's time constant is capped at the textbook slow branch's bound
MAX_TAU_DF_S = TAU2_BOUNDS_S[1]
#: the least cap ``socd fit --max-tau-df`` takes: a diffusion branch faster than the textbook
#: 2-RC's fastest branch is no longer a diffusion branch
MIN_TAU_DF_CAP_S = TAU1_BOUNDS_S[0]
#: the share of the textbook 2-RC's R0 that a fitted R_ohm keeps above the Butler-Volmer term's linear
#: drop (socd fit --pure-ohmic-share): the electrolyte and contacts conduct ohmically at any current, so
#: the kinetic term may not take the whole instantaneous drop
PURE_OHMIC_SHARE = 0.0
#: a temperature's fit is poor, and refused, when its RMSE [mV] is above both this (Zeng's bound on
#: the voltage error) and POOR_FIT_SHARE of the RMS overpotential it has to explain (a hard drive in
#: the cold moves the voltage by a volt; a fit that leaves a tenth of that is still a model of it).
#: The share is the one that passes every user fit and refuses every bad input of
#: ``research.fit_quality`` (the middle of the span that does, rounded; docs/results/characterisation.md)
POOR_FIT_MV = 50.0
POOR_FIT_SHARE = 0.6
#: the fractional fit may be worse than the textbook 2-RC fit of the same data by this much
#: (relative, and absolute mV) before the temperature is refused
ECM_TOLERANCE = (0.05, 0.5)
#: a temperature group whose samples span this much [K] (10th-90th percentile) fits the
#: resistances' activation energy too: over 3 K at 40 kJ/mol they change by about 15 %, well
#: above what a fit resolves; a chamber-held pulse test spans about 1 K
TEMPERATURE_LAW_SPAN_C = 3.0
#: the stretches a temperature's fit uses must change the current by CHANGE_MIN_C x 1C between
#: samples at least MIN_CURRENT_CHANGES times (two pulses on and off) and last MIN_FITTED_S seconds,
#: or its dynamics are not identifiable (an HPPC test's pulses give tens of such changes, a drive
#: cycle thousands)
CHANGE_MIN_C = 0.2
MIN_CURRENT_CHANGES = 4
MIN_FITTED_S = 600.0
#: a fitted CPE order this close to 1 is a capacitor (the branch is an RC branch)
ORDER_ONE_TOL = 0.02


#: the temperature group nearest this is the fit's reference: the others share its shape (``--shape``)
REFERENCE_TEMP_C = 25.0


def reference_temperature(temps_c: Iterable[float]) -> float:
    """The fit's reference temperature among ``temps_c``: the one nearest :data:`REFERENCE_TEMP_C`."""
    return min(temps_c, key=lambda t: abs(t - REFERENCE_TEMP_C))


def worse_than(rmse_mv: float, reference_mv: float) -> bool:
    """True when a fit's RMSE is worse than a reference fit's by more than :data:`ECM_TOLERANCE`."""
    rel, abs_mv = ECM_TOLERANCE
    return rmse_mv > reference_mv * (1.0 + rel) + abs_mv


class FitQualityError(ValueError):
    """A fit that must not be written as a profile; the message names the temperature(s), what
    went wrong and what data would help."""


class PoorFitError(FitQualityError):
    """A fit :func:`check_fit_quality` refuses and ``socd fit --force`` writes anyway: ``problems``
    names each temperature, what went wrong there and what data would help."""

    def __init__(self, problems: str) -> None:
        super().__init__(f"{problems}. Nothing written; --force writes the profile anyway")
        self.problems = problems


@dataclass(frozen=True)
class TemperatureFit:
    """How one temperature's fit went: both models' RMSE [mV] on the same segments."""

    temp_c: float
    rmse_mv: float
    ecm_rmse_mv: float
    at_bounds: list[str]
    #: "fractional fit"; "2-RC start" (the fractional fit did no better than its start); or
    #: "2-RC fit" (the search ended on the 2-RC submodel and the 2-RC fit's point fits as well)
    source: str
    #: RMS of the measured voltage minus the OCV at the counted SOC: what the dynamics must explain
    overpotential_rms_mv: float = 0.0
    #: the 2-RC fit's point simulated as the fractional model is (the OCV as stored, the fractional
    #: time step): the bar of :meth:`problem`, so both fits are read the same way; None: ``ecm_rmse_mv``
    ecm_simulated_mv: float | None = None
    #: the OCV at this temperature came from a table or an OCV test, not a joint fit
    ocv_measured: bool = False
    #: the point's RMSE [mV] over every segment of the recordings, where the search saw a
    #: subsample of them (:func:`service.characterisation.segment_selection.select_segments`)
    whole_rmse_mv: float | None = None

    @property
    def unexplained_share(self) -> float:
        """The fit RMSE as a share of the RMS overpotential: 0 explains every millivolt the OCV
        leaves, 1 explains none of it."""
        return self.rmse_mv / max(self.overpotential_rms_mv, 1e-9)

    def problem(self) -> str | None:
        bound = max(POOR_FIT_MV, POOR_FIT_SHARE * self.overpotential_rms_mv)
        if not np.isfinite(self.rmse_mv) or self.rmse_mv > bound:
            return (f"fit RMSE {self.rmse_mv:.1f} mV is above {bound:.0f} mV (the larger of {POOR_FIT_MV:g} mV and "
                    f"{POOR_FIT_SHARE:g} x the {self.overpotential_rms_mv:.0f} mV RMS overpotential)")
        bar = self.ecm_rmse_mv if self.ecm_simulated_mv is None else self.ecm_simulated_mv
        if worse_than(self.rmse_mv, bar):
            return (f"fit RMSE {self.rmse_mv:.1f} mV is worse than the textbook 2-RC fit of the same data "
                    f"({bar:.1f} mV as this model simulates its point; {self.ecm_rmse_mv:.1f} mV its own fit)")
        return None

    def data_hint(self) -> str:
        """What data would help a temperature whose fit has a :meth:`problem`, and the input to check
        first: a capacity 13-15 % off is refused this way in ``research.fit_quality``, with or without an
        OCV test."""
        check = ("; first check --capacity-ah (and --full-at): the fit counts every SOC with them, and a "
                 "capacity 10 % or more off can fail this way")
        if not self.ocv_measured:
            return ("an OCV test (a C/20 discharge and charge, or rests of an hour or more at five or more SOC "
                    "levels) given with --ocv or among the recordings, or an HPPC test" + check)
        return (f"the OCV there is measured, so what is left is in the dynamics (the textbook 2-RC fit leaves "
                f"{self.ecm_rmse_mv:.1f} mV): an HPPC test (current pulses from rest at several SOC levels) or "
                "drives at lower C-rates beside this one" + check)


@dataclass
class FitReport:
    lines: list[str] = field(default_factory=list)
    temperatures: list[TemperatureFit] = field(default_factory=list)
    #: where each line goes as it is said (default: stderr, prefixed ``[fit]``)
    echo: Callable[[str], None] | None = None
    #: told ``(stage, done, total)`` as each fitting stage starts (a progress bar)
    progress: Callable[[str, int, int], None] | None = None
    #: ``socd fit -q``: only notices (parameters at a bound of the search) are said; every line
    #: is still kept in ``lines``
    quiet: bool = False

    def say(self, msg: str, notice: bool = False) -> None:
        """Keep ``msg`` and say it (unless quiet and not a ``notice``)."""
        self.lines.append(msg)
        if self.quiet and not notice:
            return
        if self.echo is not None:
            self.echo(f"[fit] {msg}")
        else:
            print(f"[fit] {msg}", file=sys.stderr, flush=True)

    def stage(self, what: str, done: int, total: int) -> None:
        if self.progress is not None:
            self.progress(what, done, total)


def split_at_rests(rec: Recording, soc: np.ndarray, capacity_ah: float, min_rest_s: float = SEGMENT_REST_S,
                   track_branch: bool = False) -> list[FitSegment]:
    """Segments of ``rec`` that each start at the end of a rest of ``min_rest_s`` (or the start).

    ``track_branch`` (a one-branch OCV table): each segment starts on the hysteresis branch of
    its history (``FitSegment.u_h0_branch``).  Without it every segment starts at ``U_h`` = 0,
    as a mean table needs: a fit from a full point then reads the table as the
    branch the cell is on, which is how the bundled A123 profile was fitted."""
    # rest ends come out increasing and after sample 0, so no sort is needed
    starts = [0] + [j for _, j in rest_spans(rec, capacity_ah, min_rest_s) if j > 0] + [len(rec)]
    segs = []
    rest_a, load_a = rest_level_a(rec.current_a, capacity_ah), load_level_a(rec.current_a, capacity_ah)
    # the hysteresis branch each segment starts on: a full charge point is on the charge
    # branch; later segments on the branch of the last current before them
    full = float(soc[0]) >= FULL_SOC
    for a, b in pairwise(starts):
        if b - a >= 5 and np.abs(rec.current_a[a:b]).max() > load_a:
            branch = 0.0
            if track_branch:
                branch = last_current_direction(rec.current_a[1:a + 1], rest_a) if a > 0 else 0.0
                if branch == 0.0 and full:
                    branch = 1.0
            segs.append(FitSegment(rec.time_s[a:b], rec.current_a[a:b], rec.voltage_v[a:b],
                                   rec.temperature_c[a:b], float(soc[a]), u_h0_branch=branch))
    return segs


def measure_soc_resistance(groups: dict[float, list[tuple[Recording, np.ndarray]]], capacity_ah: float,
                           ocv: OcvTable, rep: FitReport) -> SocResistanceSpec:
    """Resistance scales over SOC per temperature group, measured from the discharge pulses
    from rest of HPPC-like recordings (:func:`service.cell.soc_dependence.pulse_resistances`),
    on a common SOC grid (end values held outside each temperature's measured range)."""
    grid = np.round(np.linspace(0.0, 1.0, SOC_RESISTANCE_POINTS), 6)
    temps, rows_ohm, rows_pol = [], [], []
    for t in sorted(groups):
        pulses = [pulse_resistances(part.time_s, part.current_a, part.voltage_v, soc, capacity_ah,
                                    rest_level_a(part.current_a, capacity_ah), ocv_v=ocv.ocv(soc, part.temperature_c))
                  for part, soc in groups[t]]
        rows = scale_rows(np.concatenate(pulses))
        if rows is None:
            names = ", ".join(part.name for part, _ in groups[t])
            raise ValueError(f"--soc-resistance: too few discharge pulses from rest at {t:g} °C in {names} "
                             "(needs an HPPC-like test: pulses at five or more SOC levels)")
        soc, g_ohm, g_pol = rows
        temps.append(t)
        rows_ohm.append(np.interp(grid, soc, g_ohm).tolist())
        rows_pol.append(np.interp(grid, soc, g_pol).tolist())
        rep.say(f"resistance over SOC at {t:g} °C from {sum(len(p) for p in pulses)} pulses at {soc.size} SOC levels: "
                + ", ".join(f"{s:.2f}: x{a:.2f}/x{b:.2f}" for s, a, b in zip(soc, g_ohm, g_pol))
                + " (R_ohm / polarisation scale)")
    return SocResistanceSpec(soc=grid.tolist(), temps_c=temps, r_ohm_scale=rows_ohm, r_pol_scale=rows_pol)


def say_flat_joint_ocv(rep: FitReport, grid: np.ndarray, rows: dict[float, np.ndarray]) -> None:
    """A notice per temperature where the jointly fitted OCV is flat (:func:`service.cell.ocv.flat_share`):
    there its monotone bound is active, the recordings do not determine the table, and a filter reading
    the slope at its estimate takes nothing from the voltage."""
    for t in sorted(rows, reverse=True):
        share = flat_share(OcvTable.from_points(grid, rows[t]), t)  # a one-row table: any temperature reads it
        if share > 0:
            rep.say(f"  {t:g} °C: the joint OCV is flat over {100 * share:.0f} % of SOC (held up by its monotone "
                    "bound where the data would have it fall); the SOC filter takes little from the voltage "
                    "on its flattest runs (flat_ocv_noise_v), and an OCV test or rests at those SOCs would "
                    "determine it", notice=True)


def characterise(
    recordings: list[Recording],
    capacity_ah: float,
    full_at: list[str | float | None],
    ocv_table: tuple[np.ndarray, np.ndarray] | None = None,
    fit_hysteresis: bool = False,
    fit_kinetics: bool | None = None,
    max_seconds: float = 60.0,
    min_order: float | None = None,
    min_slow_order: float | None = None,
    monotone: bool = False,
    soc_resistance: bool = False,
    memory_length: int = 16,
    name: str = "cell",
    seed: int = 0,
    starts: int = 1,
    slow_branch: bool = False,
    ocv_branch: str = "mean",
    rest_anchor: bool | None = None,
    short_charge: bool = False,
    max_tau_df_s: float = MAX_TAU_DF_S,
    pure_ohmic_share: float = PURE_OHMIC_SHARE,
    ocv_beyond: str = "hold",
    ocv_between_rests: str | None = None,
    ocv_smoothing: float | None = None,
    force_capacity: bool = False,
    shape: str = DEFAULT_SHAPE,
    report: FitReport | None = None,
) -> tuple[CellProfile, FitReport]:
    """Fit a cell profile (``socd fit``).  ``ocv_branch``: which hysteresis branch the OCV
    table or test is (:class:`HysteresisSpec` ``table_branch``; needs ``fit_hysteresis``
    unless ``mean``).  ``rest_anchor``: a jointly fitted OCV table (no table, no OCV test) is
    shifted at each temperature to pass through the voltages that temperature's long rests (one
    or more) relax towards, before the parameters are fitted on it (the order of OCV sources: an
    OCV test, else the rests, else the joint fit).  ``None`` (the default) anchors where
    the table is fitted jointly and a long rest exists; ``True`` requires both; ``False`` keeps the
    joint table and only reports its offsets from the rests.  ``fit_kinetics``: fit the Butler-Volmer
    exchange current at every temperature (True), at none (False), or (None, the default) at each
    temperature whose recordings have the current steps that resolve it (:func:`kinetics_resolvable`).
    ``short_charge``: an OCV test whose charge stopped short of full is counted on the discharge's
    scale (:func:`ocv_from_test`).  ``max_tau_df_s``: cap on the fractional diffusion branch's time
    constant (:func:`service.cell.fitting.diffusion_tau`).  ``pure_ohmic_share``: the share of the
    textbook 2-RC's ``R0`` at each temperature that ``R_ohm`` keeps above the Butler-Volmer term's linear
    drop (:func:`service.cell.profile.ohmic_floor_ohm`).  ``ocv_beyond``: how OCV tests' rows are
    read at temperatures beyond theirs (:func:`ocv_rows_by_temperature`).  ``ocv_between_rests``: how
    a rest-anchored joint OCV is read between rests close in SOC (:func:`reads_through_rests`); ``None``
    (the default) reads it the :data:`DEFAULT_OCV_BETWEEN_RESTS` way where there is such an OCV and
    leaves any other OCV alone, while a choice named where there is none is an error.
    ``force_capacity``: fit with ``capacity_ah`` even where a room-temperature OCV test moved
    less charge than that by more than the tolerance (:func:`capacity_above_test`, ``socd fit --force``;
    the fit log says so, as it does for any excess above the notice level).
    ``shape``: which of the fractional point's shape coordinates the reference temperature's
    point fixes at the other temperatures (:data:`SHAPES`; :func:`shape_pins`).
    ``ocv_smoothing``: the smoothness weight of a jointly fitted OCV (:func:`fit_ecm2rc`; ``None``:
    :data:`OCV_SMOOTH_WEIGHT`), an error where the OCV is given.  ``starts``:
    global searches per temperature, seeded ``seed``, ``seed + 1``, ...; the point that fits the
    temperature's segments best is kept (the searches end on different points where the data pin the
    parameters down poorly)."""
    if ocv_branch != "mean" and not fit_hysteresis:
        raise ValueError(f"an OCV table on the {ocv_branch} branch needs the hysteresis fitted (--hysteresis)")
    if shape not in SHAPES:
        raise ValueError(f"unknown shape {shape!r}; one of {', '.join(SHAPES)}")
    rep = report if report is not None else FitReport()
    ocv_tests = [r for r in recordings if is_ocv_test(r, capacity_ah)]
    if rest_anchor is True and (ocv_table is not None or ocv_tests):
        raise ValueError("--rest-anchor anchors a jointly fitted OCV table; with an OCV table or test given, "
                         "the table is already shifted to the rests of each temperature")
    if ocv_between_rests is not None and (ocv_table is not None or ocv_tests or rest_anchor is False):
        given = "--no-rest-anchor" if rest_anchor is False else "an OCV table or test"
        raise ValueError(f"--ocv-between-rests {ocv_between_rests} reads between the rests of a jointly fitted, "
                         f"rest-anchored OCV; with {given} there is none")
    if ocv_smoothing is not None and (ocv_table is not None or ocv_tests):
        raise ValueError(f"--ocv-smoothing {ocv_smoothing:g} smooths a jointly fitted OCV; with an OCV table or test "
                         "given there is none")
    smooth_weight = OCV_SMOOTH_WEIGHT if ocv_smoothing is None else ocv_smoothing
    dynamic = [(r, fa) for r, fa in zip(recordings, full_at) if not is_ocv_test(r, capacity_ah)]
    if not dynamic:
        raise ValueError("socd fit needs at least one dynamic recording (drive cycle or HPPC) to fit the model")
    grid = np.linspace(0.0, 1.0, GRID_POINTS)
    #: OCV rows by the temperature they were measured at (a given table: at every temperature)
    test_rows: dict[float, np.ndarray] | None = None
    if ocv_table is not None:
        test_rows = {25.0: make_monotone(np.interp(grid, *ocv_table))}
        rep.say("OCV: from the given table")
    elif ocv_tests:
        by_t: dict[float, list[np.ndarray]] = defaultdict(list)
        for r in ocv_tests:
            curve = ocv_from_test(r, capacity_ah, grid, short_charge)
            above = capacity_above_test(str(r.path), curve, float(np.median(r.temperature_c)), capacity_ah)
            if above is not None:
                if above.refused and not force_capacity:
                    raise ValueError(f"{above.text}; --force fits with the one given")
                lead = f"--force fits with --capacity-ah {capacity_ah:g} although " if above.refused else "notice: "
                rep.say(lead + above.text, notice=True)
            by_t[temperature_group(r)].append(curve.ocv_v)
            if curve.charge_reach < 1.0:
                rep.say(f"OCV: {r.name}'s charge stopped short of full, at {100 * curve.charge_reach:.1f} % of the "
                        "discharge's capacity; " + ("counted on the discharge's scale" if curve.short_charge else
                                                    "stretched over the whole range (--short-charge counts it on "
                                                    "the discharge's scale)"))
        test_rows = {t: np.mean(rows, axis=0) for t, rows in by_t.items()}
        rep.say(f"OCV: from OCV test(s) {', '.join(r.name for r in ocv_tests)} at "
                f"{', '.join(f'{t:g}' for t in sorted(test_rows))} °C")

    # dynamic recordings grouped by temperature, cut from their full-charge point
    groups: dict[float, list[tuple[Recording, np.ndarray]]] = defaultdict(list)
    whole: dict[float, list[Recording]] = defaultdict(list)  # the same recordings before the cut
    for rec, fa in dynamic:
        part, soc = truth_and_start(rec, capacity_ah, fa)
        check_counted_soc(part, capacity_ah, float(soc[0]))
        key = temperature_group(part)
        groups[key].append((part, soc))
        whole[key].append(rec)
    temps = sorted(groups)
    ref_t = reference_temperature(temps)
    rep.say(f"temperature groups (each recording's median measured temperature, to {TEMP_GROUP_C:g} °C): "
            f"{', '.join(f'{t:g} °C ({len(groups[t])} rec.)' for t in temps)}; reference {ref_t:g} °C")
    extra_branches: list[BranchSpec] = []
    slow_note = None
    if slow_branch:
        slow = measure_slow_relaxation(whole[ref_t], capacity_ah)
        extra_branches.append(slow.branch())
        slow_note = slow.describe()
        rep.say(f"slow relaxation branch (long rests at {ref_t:g} °C): {slow_note}")

    def all_segments_of(t: float) -> list[FitSegment]:
        segs: list[FitSegment] = []
        for part, soc in groups[t]:
            segs += [s for s in split_at_rests(part, soc, capacity_ah, track_branch=ocv_branch != "mean")
                     if s.soc0 >= MIN_FIT_SOC]
        return segs

    def template(ocv_rows: dict[float, np.ndarray]) -> CellProfile:
        ts = sorted(ocv_rows)
        return CellProfile(
            name=name, capacity_ah=capacity_ah,
            ocv=OcvSpec(soc=grid.tolist(), temps_c=ts, ocv_v=[ocv_rows[t].tolist() for t in ts]),
            parameters=[ParameterPoint(r_ohm=0.02, r_ct=0.01, c_dl=500, m=0.8, r_df=0.02, c_df=5000, n=0.6)],
            extensions=Extensions(extra_branches=extra_branches),
            hysteresis=HysteresisSpec(table_branch=ocv_branch),
        )

    # rest points per group → OCV rows
    ocv_rows: dict[float, np.ndarray] = {}
    def rests_by_t(extrapolate: bool = False) -> dict[float, list]:
        """Each temperature's long rests: where they stopped, or (``extrapolate``) their relaxation limits."""
        return {t: [p for part, soc in groups[t]
                    for p in rest_points(part, capacity_ah, float(soc[0]), extrapolate=extrapolate)] for t in temps}

    if test_rows is not None:
        points_by_t = rests_by_t()
        base_at = ocv_rows_by_temperature(test_rows, temps, ocv_beyond)
        for t in temps:
            ocv_rows[t] = ocv_row_from_rests(grid, base_at[t], points_by_t[t])
            if len(points_by_t[t]) >= 3:
                say_rest_alignment(rep, t, grid, base_at[t], points_by_t[t], capacity_ah)
    # the textbook 2-RC model on the same segments: the bar the fractional fit must clear, and
    # (with no OCV table or test) the monotone joint OCV the fractional fit starts from
    ecm: dict[float, Ecm2RcFit] = {}
    order = sorted(temps, key=lambda t: abs(t - ref_t))  # reference first, then outwards
    every_seg_at = {t: all_segments_of(t) for t in order}
    segs_at = {t: select_segments(every_seg_at[t], MAX_FIT_SAMPLES) for t in order}
    memory_span_s = fitted_memory_span_s([s for segs in segs_at.values() for s in segs], memory_length, rep)
    n_stages = 2 * len(temps)
    for k, t in enumerate(order):
        rep.stage(f"2-RC fit at {t:g} °C", k, n_stages)
        segs = segs_at[t]
        if not segs:
            names = ", ".join(part.path.name for part, _ in groups[t])
            raise FitQualityError(f"{names}: no stretch of these recordings at {t:g} °C starts from a known state above SOC "
                                  f"{MIN_FIT_SOC:g} with current on it: nothing to fit there"
                                  + peak_c_rate_note(groups[t], capacity_ah))
        check_excitation(t, segs, groups[t], capacity_ah)
        if test_rows is not None:
            ecm[t] = fit_ecm2rc(segs, capacity_ah, ocv_soc=grid, ocv_v=ocv_rows[t])
        else:
            prior = None if t == ref_t else ecm[ref_t].ocv_v
            ecm[t] = fit_ecm2rc(segs, capacity_ah, prior_v=prior, smooth_weight=smooth_weight)
        f = ecm[t]
        rep.say(f"textbook 2-RC at {t:g} °C: R0 {f.r0 * 1e3:.1f} mΩ, R1 {f.r1 * 1e3:.1f} mΩ / τ1 {f.tau1_s:.1f} s, "
                f"R2 {f.r2 * 1e3:.1f} mΩ / τ2 {f.tau2_s:.0f} s; fit RMSE {f.rmse_mv:.1f} mV"
                + (" (OCV fitted jointly)" if test_rows is None else ""))
    # the 2-RC model's own OCV: the given one, or its joint fit (before any --rest-anchor shift)
    ecm_rows = {t: ocv_rows[t] if test_rows is not None else make_monotone(ecm[t].ocv_on(grid)) for t in temps}
    if test_rows is None:
        rep.say("OCV: no table or OCV test given: the monotone OCV fitted jointly with the textbook 2-RC model "
                "at each temperature")
        say_flat_joint_ocv(rep, grid, ecm_rows)
        ocv_rows.update(ecm_rows)
        # the voltage each rest relaxes towards, not where it stopped (cold rests end unrelaxed)
        limits_by_t = rests_by_t(extrapolate=True)
        if rest_anchor is True or (rest_anchor is None and any(limits_by_t.values())):
            anchor_rows_at_rests(rep, grid, ocv_rows, limits_by_t,
                                 ocv_between_rests or DEFAULT_OCV_BETWEEN_RESTS, ref_t)
        elif rest_anchor is None:
            rep.say(f"OCV: no rest of {REST_MIN_S:g} s or more to anchor the joint table at; it stands as fitted")
        else:
            say_joint_ocv_at_rests(rep, grid, ocv_rows, limits_by_t)
    ecm_spec = Ecm2RcSpec(
        ocv=OcvSpec(soc=grid.tolist(), temps_c=temps,
                    ocv_v=[ecm_rows[t].tolist() for t in temps]),
        points=[Ecm2RcPoint(temp_c=t, r0=max(ecm[t].r0, 1e-6), r1=ecm[t].r1, tau1_s=ecm[t].tau1_s, r2=ecm[t].r2,
                            tau2_s=ecm[t].tau2_s, fit_rmse_mv=round(ecm[t].rmse_mv, 3)) for t in temps],
    )

    prof = template(ocv_rows)
    if soc_resistance:
        spec = measure_soc_resistance(groups, capacity_ah, prof.ocv_table(), rep)
        prof = prof.model_copy(update={"extensions": prof.extensions.model_copy(update={"soc_resistance": spec})})
    points: dict[float, ParameterPoint] = {}
    hyst: HysteresisSpec | None = None
    for k, t in enumerate(order):
        rep.stage(f"fractional fit at {t:g} °C", len(temps) + k, n_stages)
        segs = segs_at[t]
        rep.say(f"fitting parameters at {t:g} °C on {len(segs)} segment(s), {sum(len(s) for s in segs)} samples "
                f"(≤ {max_seconds:g} s)...")
        warmer = colder = None
        if monotone:
            # resistances monotone in temperature: bounded by the nearest fitted warmer / colder point
            warmer = min((p for tp, p in points.items() if tp > t), key=lambda p: p.temp_c, default=None)
            colder = max((p for tp, p in points.items() if tp < t), key=lambda p: p.temp_c, default=None)
        kinetics_t = (fit_kinetics if fit_kinetics is not None
                      else kinetics_resolvable([part for part, _ in groups[t]], capacity_ah, t, rep))
        start = ecm_start_point(ecm[t], t, max_tau_df_s=max_tau_df_s)
        law_t = temperature_law_resolvable(segs, t, rep)
        # the search coordinates the reference temperature's point holds here (--shape)
        pins = {} if t == ref_t else shape_pins(points[ref_t], shape)
        search = {"min_pure_ohm": pure_ohmic_share * ecm[t].r0, "fit_hysteresis": fit_hysteresis and t == ref_t,
                  "max_seconds": max_seconds, "x0": start, "warmer": warmer, "colder": colder, "min_order": min_order,
                  "min_slow_order": min_slow_order, "max_tau_df_s": max_tau_df_s, "temperature_law": law_t,
                  "law_ref_temp_c": t, "pinned": pins or None}
        res, pt, rmse = best_of_starts(prof, segs, t, seed, starts, rep, memory_length, fit_kinetics=kinetics_t,
                                       **search)
        if kinetics_t and fit_kinetics is None and res.i0_at_lower_bound:
            say_exchange_current_unmeasured(rep, t, pt)
            kinetics_t = False
            res, pt, rmse = best_of_starts(prof, segs, t, seed, starts, rep, memory_length, fit_kinetics=False,
                                           **search)
        ea_t = res.ea_j_mol
        # the 2-RC fit's point read as this model reads a point (the OCV as stored, the fractional
        # time step, no hysteresis): the bar the fit is held to, both read the same way
        ecm_point = ecm_start_point(ecm[t], t, linear_kinetics=kinetics_t, max_tau_df_s=max_tau_df_s)
        start_rmse = segments_rmse_mv(prof, ecm_point, prof.hysteresis, segs, memory_length)
        if worse_than(start_rmse, ecm[t].rmse_mv):
            rep.say(f"  {t:g} °C: the 2-RC point reads {start_rmse:.1f} mV as this model simulates it, against "
                    f"{ecm[t].rmse_mv:.1f} mV in its own fit: the stored OCV table and the fractional time step "
                    "lose that much; the fit is held to the simulated figure")
        source = "fractional fit"
        if not (fit_hysteresis and t == ref_t):
            # the search may end worse than the point it started from (a time-bounded global
            # stage on windows): keep whichever fits the whole segments better
            if start_rmse < rmse:
                pt, rmse, source, ea_t = ecm_point, start_rmse, "2-RC start", None
            elif test_rows is None and on_2rc_submodel(pt) and not worse_than(start_rmse, rmse):
                # the search ended on the 2-RC submodel with the OCV the 2-RC fit chose jointly
                # with its own point: the two belong together (the linear fit's optimum is the
                # global one over every sample), so keep that point. With a measured OCV there
                # is no such bond, and the better fit stands.
                pt, rmse, source, ea_t = ecm_point, start_rmse, "2-RC fit", None
        points[t] = pt
        if res.hysteresis is not None:
            hyst = res.hysteresis
        whole = None
        if len(segs) < len(every_seg_at[t]):
            # the search saw a subsample: read the point on every segment too, so a subsample
            # that does not stand for the recording shows in the log
            read_hyst = res.hysteresis if source == "fractional fit" and res.hysteresis is not None else prof.hysteresis
            whole = segments_rmse_mv(prof, pt, read_hyst, every_seg_at[t], memory_length, ea_t)
        outcome = TemperatureFit(temp_c=t, rmse_mv=rmse, ecm_rmse_mv=ecm[t].rmse_mv, ecm_simulated_mv=start_rmse,
                                 at_bounds=res.at_bounds if source == "fractional fit" else [], source=source,
                                 overpotential_rms_mv=overpotential_rms_mv(prof, segs),
                                 ocv_measured=test_rows is not None, whole_rmse_mv=whole)
        rep.temperatures.append(outcome)
        rep.say(f"  {t:g} °C: R_ohm {pt.r_ohm * 1e3:.1f} mΩ, R_ct {pt.r_ct * 1e3:.1f} mΩ, m {pt.m:.2f}, "
                f"R_df {pt.r_df * 1e3:.1f} mΩ, n {pt.n:.2f}"
                + (f", i0 {pt.i0_a:.2f} A" if pt.i0_a is not None else "")
                + (f", Ea {ea_t / 1000:.0f} kJ/mol over the group's temperatures" if ea_t is not None else "")
                + f"; fit RMSE {rmse:.1f} mV (textbook 2-RC {ecm[t].rmse_mv:.1f} mV, {start_rmse:.1f} mV as this "
                  "model simulates its point)"
                + f", {outcome.unexplained_share:.0%} of the {outcome.overpotential_rms_mv:.0f} mV RMS overpotential"
                + {"2-RC start": " from the 2-RC start point",
                   "2-RC fit": " (the search ended on the 2-RC submodel: orders 1, linear kinetics; the 2-RC "
                               "fit's own point is kept)"}.get(source, "")
                + (f"; search stopped at its {max_seconds:g} s bound (--max-seconds)" if res.time_bound
                   else f"; search finished in {res.seconds:.0f} s"))
        if whole is not None:
            every = every_seg_at[t]
            rep.say(f"  {t:g} °C: the search saw {len(segs)} of {len(every)} segments "
                    f"({sum(len(x) for x in segs)} of {sum(len(x) for x in every)} samples, stratified by kind of "
                    f"segment); on all of them the point reads {whole:.1f} mV")
        if outcome.at_bounds:
            rep.say(f"  {t:g} °C: at a bound of the search: {', '.join(outcome.at_bounds)}", notice=True)
        if pins and not np.allclose(list(shape_pins(pt, shape).values()), list(pins.values()), atol=1e-6):
            say_shape_not_shared(rep, t, ref_t, shape, source, max_tau_df_s)
    say_exchange_current_rising_in_the_cold(rep, points)
    profile = prof.model_copy(update={
        "memory_span_s": memory_span_s,
        "parameters": with_linear_kinetics_where_unfitted([points[t] for t in sorted(points)]),
        "hysteresis": hyst or HysteresisSpec(table_branch=ocv_branch),
        "ecm2rc": ecm_spec,
        "notes": {"fitted_from": ", ".join(r.name for r in recordings), "memory_length": str(memory_length)}
        | ({"slow_branch": slow_note} if slow_note else {}),
    })
    rep.stage("done", n_stages, n_stages)
    return CellProfile.model_validate(profile.model_dump()), rep


def best_of_starts(prof: CellProfile, segs: list[FitSegment], temp_c: float, seed: int, starts: int,
                   rep: FitReport, memory_length: int, min_pure_ohm: float = 0.0,
                   **fit_options) -> tuple[FitResult, ParameterPoint, float]:
    """``starts`` searches (:func:`fit_parameters` with ``memory_length`` and ``fit_options``) seeded ``seed``, ``seed + 1``,
    ...: the result, its point relabelled to ``temp_c`` and that point's RMSE over ``segs`` (mV), of
    the one that fits ``segs`` best. With several, the log gives each search's RMSE and the
    polarisation its point predicts under a sustained load (:mod:`.sustained_load`), and a notice when
    the searches that fit alike predict it further apart than the fit's RMSE."""
    fits = []
    for j in range(max(1, starts)):
        res = fit_parameters(prof, segs, memory_length=memory_length, seed=seed + j, min_pure_ohm=min_pure_ohm,
                             **fit_options)
        # relabelled to the group's temperature: R_ohm again holds the linear kinetic drop there
        pt = lift_to_ohmic_floor(res.point.model_copy(update={"temp_c": temp_c}), res.point.i0_a,
                                 prof.min_r_ohm_scale(temp_c), min_pure_ohm)
        rmse = segments_rmse_mv(prof, pt, res.hysteresis or prof.hysteresis, segs, memory_length, res.ea_j_mol)
        fits.append((res, pt, rmse))
    keep = min(range(len(fits)), key=lambda j: fits[j][2])
    if len(fits) == 1:
        return fits[keep]
    polarisation = [sustained_polarisation_mv(prof, pt, res.hysteresis or prof.hysteresis, memory_length)
                    for res, pt, _ in fits]
    load = f"after {SUSTAINED_S / 60:g} min at {SUSTAINED_C_RATE:g}C"
    for j, ((_, _, rmse), pol) in enumerate(zip(fits, polarisation)):
        rep.say(f"  {temp_c:g} °C: search {j + 1} of {len(fits)} (seed {seed + j}) fits to {rmse:.2f} mV; "
                f"{pol:.0f} mV polarisation {load}" + (" (kept)" if j == keep else ""))
    spread = polarisation_spread_mv([rmse for *_, rmse in fits], polarisation)
    if spread > fits[keep][2]:
        rep.say(f"  {temp_c:g} °C: searches that fit alike predict polarisations {spread:.0f} mV apart {load}, more "
                f"than the fit's {fits[keep][2]:.1f} mV RMSE: the recordings leave the slow polarisation open here "
                "(a drive cycle or a long constant-current discharge at this temperature would pin it)", notice=True)
    return fits[keep]


def polarisation_spread_mv(rmse_mv: list[float], polarisation_mv: list[float]) -> float:
    """How far apart [mV] the searches whose RMSE is not :func:`worse_than` the best's predict the
    polarisation under a sustained load: what the recordings fit alike and do not determine."""
    best = min(rmse_mv)
    near = [p for r, p in zip(rmse_mv, polarisation_mv) if not worse_than(r, best)]
    return max(near) - min(near)


def fitted_memory_span_s(segments: list[FitSegment], memory_length: int, rep: FitReport) -> float | None:
    """The G-L memory the fit runs with, in seconds: ``memory_length`` samples at the segments'
    sample period (the median interval over all of them), stored in the profile so the
    estimators keep that span at their own sample period (:mod:`service.cell.memory`)."""
    dt = np.concatenate([np.diff(s.time_s) for s in segments]) if segments else np.zeros(0)
    period = median_interval_s(dt)
    if period is None:
        return None
    span = memory_length * period
    rep.say(f"G-L memory: {memory_length} samples at the recordings' {period:.3g} s sample period, {span:.3g} s; "
            "the estimators keep that span at their own sample period")
    return round(span, 6)


def temperature_group(rec: Recording) -> float:
    """The temperature a recording is grouped at: its median, to :data:`TEMP_GROUP_C`."""
    return float(TEMP_GROUP_C * np.round(np.median(rec.temperature_c) / TEMP_GROUP_C)) + 0.0  # no -0 °C


def check_excitation(temp_c: float, segments: list[FitSegment], recordings: list[tuple[Recording, np.ndarray]],
                     capacity_ah: float) -> None:
    """Refuse a temperature whose recordings cannot identify the model: in the stretches the fit uses,
    fewer than :data:`MIN_CURRENT_CHANGES` changes of the current by :data:`CHANGE_MIN_C` × 1C between
    samples, or under :data:`MIN_FITTED_S` seconds.  A constant-current discharge or a minute of a drive
    would otherwise give a profile whose resistances and time constants are whatever the search
    started from."""
    changes = sum(int(np.sum(np.abs(np.diff(s.current_a)) >= CHANGE_MIN_C * capacity_ah)) for s in segments)
    seconds = sum(float(s.time_s[-1] - s.time_s[0]) for s in segments)
    if changes < MIN_CURRENT_CHANGES or seconds < MIN_FITTED_S:
        names = ", ".join(part.path.name for part, _ in recordings)
        raise FitQualityError(
            f"{names}: at {temp_c:g} °C the recordings hold {changes} change(s) of the current by "
            f"{CHANGE_MIN_C:g}C or more in {seconds:.0f} s; fitting the dynamics needs {MIN_CURRENT_CHANGES} in "
            f"{MIN_FITTED_S:g} s or more (a drive cycle, an HPPC or a pulse test){peak_c_rate_note(recordings, capacity_ah)}; "
            "nothing written")


def peak_c_rate_note(recordings: list[tuple[Recording, np.ndarray]], capacity_ah: float) -> str:
    """`` (the largest current there is 4.1 A, 0.21C of --capacity-ah 20)``: every C-rate rule reads the
    current through the capacity, so a capacity given wrong shows here first."""
    peak = max((float(np.max(np.abs(part.current_a))) for part, _ in recordings if len(part)), default=0.0)
    return f" (the largest current there is {peak:.3g} A, {peak / capacity_ah:.2g}C of --capacity-ah {capacity_ah:g})"


def check_counted_soc(part: Recording, capacity_ah: float, soc0: float) -> None:
    """The models count charge with ``capacity_ah`` from ``soc0``: a count that leaves [0, 1] by
    more than :data:`service.cell.truth.COUNTED_SOC_MARGIN` means the capacity or the full-charge point is wrong,
    and a fit on it would bend the OCV to match (refused, naming the recording)."""
    counted = coulomb_soc(part.time_s, part.current_a, capacity_ah, soc0)
    if (where := counted_soc_excursion(counted)) is not None:
        raise FitQualityError(
            f"{part.path}: SOC counted with --capacity-ah {capacity_ah:g} from {soc0:.2f} at the start reaches "
            f"{where}: the capacity is wrong for this cell or the full-charge point (--full-at) is{count_hint(part)}; "
            "nothing written")


def kinetics_resolvable(recordings: list[Recording], capacity_ah: float, temp_c: float, rep: FitReport) -> bool:
    """Whether a temperature's recordings (each cut from its full-charge point) resolve the
    Butler-Volmer exchange current: enough clean current steps, reaching high enough
    (:func:`service.cell.current_steps.steps_resolve_kinetics`, the rule the diagnosis's kinetics
    signature reads). Without them the extra parameter is not measured, and the search uses it to
    absorb other model error."""
    n_steps, peak = 0, 0.0
    for rec in recordings:
        steps = current_steps(rec.time_s, rec.current_a, capacity_ah)
        n_steps += int(steps.size)
        peak = max(peak, steps_peak_c(rec.current_a, steps, capacity_ah))
    resolved = steps_resolve_kinetics(n_steps, peak)
    rep.say(f"kinetics at {temp_c:g} °C: {n_steps} current steps reaching {peak:.2f}C: "
            + ("exchange current fitted" if resolved else
               f"not fitted (needs {STEP_MIN_STEPS} reaching {STEP_MIN_PEAK_C:g}C; --kinetics fits it anyway)"))
    return resolved


def temperature_law_resolvable(segments: list[FitSegment], temp_c: float, rep: FitReport) -> bool:
    """Whether a temperature group's segments move enough in temperature (the 10th to 90th
    percentile of their samples at least :data:`TEMPERATURE_LAW_SPAN_C`) to measure how the
    resistances change with it; a drive cycle in the cold warms the cell by 10-20 K, a pulse test
    in a chamber by about one."""
    temps = np.concatenate([s.temperature_c for s in segments])
    span = float(np.percentile(temps, 90) - np.percentile(temps, 10))
    resolved = span >= TEMPERATURE_LAW_SPAN_C
    if resolved:
        rep.say(f"temperature at {temp_c:g} °C spans {span:.1f} K (10th-90th percentile): the resistances' "
                "activation energy is fitted with the point")
    return resolved


def say_exchange_current_unmeasured(rep: FitReport, temp_c: float, point: ParameterPoint) -> None:
    """A notice that a temperature's exchange current ended on the search's lower bound, so that
    temperature is fitted again with linear kinetics. At that bound the Butler-Volmer term takes
    nearly the whole instantaneous drop as a logarithm of the current, and the drop vanishes the
    moment the current stops: the fit used the term to stand in for polarisation that outlasts the
    pulse (which a drive's short stops then show), not to measure i0."""
    rep.say(f"  {temp_c:g} °C: the exchange current i0 ended at {point.i0_a:.3g} A, the search's lower bound: the "
            "pulses ask for more curvature than the Butler-Volmer term may give, so it is not measured; fitting "
            "this temperature again with linear kinetics (--kinetics keeps it)", notice=True)


def say_exchange_current_rising_in_the_cold(rep: FitReport, points: dict[float, ParameterPoint]) -> None:
    """A notice for each pair of neighbouring temperatures that fitted a Butler–Volmer exchange current
    (not the linear placeholder) where the colder one's is larger: ``i0`` falls as a cell cools
    (Arrhenius), so the recordings did not pin it at one of the two, and the profile's kinetics between
    them interpolates a compromise of the search."""
    fitted = [(t, p.i0_a) for t, p in sorted(points.items()) if not kinetics_linear(p)]
    for (t_cold, i_cold), (t_warm, i_warm) in pairwise(fitted):
        if i_cold > i_warm:
            rep.say(f"exchange current i0 is {i_cold:.2f} A at {t_cold:g} °C but {i_warm:.2f} A at {t_warm:g} °C: "
                    "it should fall as a cell cools, so the recordings do not pin it at one of the two (current "
                    "pulses of several sizes at both temperatures would)", notice=True)


def with_linear_kinetics_where_unfitted(points: list[ParameterPoint]) -> list[ParameterPoint]:
    """A profile carries i0 at every temperature or at none: where some temperatures fitted it and
    others did not, the others get the search's largest exchange current (practically linear, the
    point unchanged)."""
    if all(p.i0_a is None for p in points) or all(p.i0_a is not None for p in points):
        return points
    return [p if p.i0_a is not None else p.model_copy(update={"i0_a": LINEAR_I0_A}) for p in points]


def reads_through_rests(between: str, temp_c: float, ref_t: float, anchors: list[RestPoint]) -> bool:
    """Whether the OCV row at ``temp_c`` is read through its rests (``--ocv-between-rests``): everywhere
    (``interpolate``), within :data:`NEAR_REFERENCE_K` of the reference temperature ``ref_t``
    (``near-reference``, ``reference-shape``), where the rests have settled (``settled``,
    :func:`rests_settled`), or nowhere (``joint``)."""
    return (between == "interpolate"
            or (between in ("near-reference", "reference-shape") and abs(temp_c - ref_t) <= NEAR_REFERENCE_K)
            or (between == "settled" and rests_settled(anchors)))


def anchor_rows_at_rests(rep: FitReport, grid: np.ndarray, ocv_rows: dict[float, np.ndarray],
                         points_by_t: dict[float, list], between: str, ref_t: float) -> None:
    """The rest anchor (``socd fit``'s default, ``--rest-anchor``): each temperature's jointly
    fitted OCV row shifted through the relaxed voltages of that temperature's long rests
    (``points_by_t``; :func:`ocv_row_from_rests`, one rest is enough); a temperature without one
    keeps its row.  Between rests close in SOC the row is then the monotone cubic through them
    (:func:`interpolate_between_rests`) instead of the joint fit's shape where
    :func:`reads_through_rests` says so for ``between``; with ``reference-shape``, a temperature more than
    :data:`NEAR_REFERENCE_K` from the reference is the reference's finished row shifted through its own
    rests instead.  No rest at any temperature is an error."""
    if not any(points_by_t.values()):
        raise ValueError(f"--rest-anchor: no rest of {REST_MIN_S:g} s or more in the recordings at any temperature "
                         f"({', '.join(f'{t:g} °C' for t in sorted(points_by_t))}) to anchor the OCV table on")
    # the reference first: ``reference-shape`` reads the far temperatures with its finished row
    for t in sorted(points_by_t, key=lambda t: abs(t - ref_t)):
        anchors = points_by_t[t]
        if not anchors:
            rep.say(f"{t:g} °C: no rest of {REST_MIN_S:g} s or more; its jointly fitted OCV is kept")
            continue
        if between == "reference-shape" and abs(t - ref_t) > NEAR_REFERENCE_K and points_by_t.get(ref_t):
            ocv_rows[t] = ocv_row_from_rests(grid, ocv_rows[ref_t], anchors, min_points=1)
            rep.say(f"{t:g} °C: more than {NEAR_REFERENCE_K:g} K from the reference {ref_t:g} °C, so the OCV is the "
                    f"reference's row shifted through this temperature's rests ("
                    + rest_offsets_text(grid, ocv_rows[ref_t], anchors, "") + " from the reference's row)")
            continue
        rep.say(f"joint OCV at {t:g} °C anchored at the relaxed rest voltage(s) of "
                + rest_offsets_text(grid, ocv_rows[t], anchors, "the table moved"))
        ocv_rows[t] = ocv_row_from_rests(grid, ocv_rows[t], anchors, min_points=1)
        row = interpolate_between_rests(grid, ocv_rows[t], anchors)
        moved = float(np.max(np.abs(row - ocv_rows[t])))
        if moved > 0 and reads_through_rests(between, t, ref_t, anchors):
            rep.say(f"{t:g} °C: between rests at most {REST_INTERP_MAX_GAP:g} apart in SOC, the OCV is the "
                    f"monotone cubic through them (moved the row by up to {1000 * moved:.1f} mV)")
            ocv_rows[t] = row
        elif moved > 0 and between == "near-reference":
            rep.say(f"{t:g} °C: more than {NEAR_REFERENCE_K:g} K from the reference {ref_t:g} °C, so between its "
                    "rests the OCV keeps the joint fit's shape (the cubic through them would move it by up to "
                    f"{1000 * moved:.1f} mV; --ocv-between-rests interpolate reads through them)")


def say_joint_ocv_at_rests(rep: FitReport, grid: np.ndarray, ocv_rows: dict[float, np.ndarray],
                           points_by_t: dict[float, list]) -> None:
    """With ``--no-rest-anchor``: how far each temperature's jointly fitted OCV row sits from the
    relaxed voltages of that temperature's long rests (``points_by_t``, the same points the flag
    would anchor at), so a user sees what the flag would move (below the lowest fitted stretch
    the joint row is extrapolated)."""
    for t in sorted(points_by_t):
        if points_by_t[t]:
            rep.say(f"{t:g} °C: relaxed voltage minus the joint OCV over "
                    + rest_offsets_text(grid, ocv_rows[t], points_by_t[t], "")
                    + " (each rest's relaxation limit; without --no-rest-anchor the table goes through them)")


def rest_offsets_text(grid: np.ndarray, row: np.ndarray, anchors: list, lead: str) -> str:
    """``n rest(s) from SOC a to b: <lead> x to y mV``: each rest's relaxed voltage minus ``row``."""
    off = [1000 * (a.ocv_v - np.interp(a.soc, grid, row)) for a in anchors]
    socs = [a.soc for a in anchors]
    return (f"{len(anchors)} rest(s) from SOC {min(socs):.3f} to {max(socs):.3f}: "
            f"{(lead + ' ') if lead else ''}{min(off):+.1f} to {max(off):+.1f} mV")


def say_shape_not_shared(rep: FitReport, temp_c: float, ref_t: float, shape: str, source: str,
                         max_tau_df_s: float) -> None:
    """A notice where a temperature's kept point does not hold the reference's shape coordinates:
    the 2-RC point was kept over the search's, or (the search's own point) the diffusion time
    constant's cap held tau_df below tau_ct times the reference's ratio (:func:`diffusion_tau`)."""
    if source == "fractional fit":
        why = (f"the diffusion time constant's cap ({max_tau_df_s:g} s, --max-tau-df) holds it below the charge-"
               "transfer one times the held ratio, so the ratio is not shared here (a larger --max-tau-df, or "
               "--shape orders)")
    else:
        why = ("the search holding it fitted worse than the 2-RC point, which is kept, so this temperature does not "
               "share that shape (more --max-seconds, or --shape each)")
    rep.say(f"  {temp_c:g} °C: the {ref_t:g} °C point's shape (--shape {shape}): {why}", notice=True)


def shape_pins(reference: ParameterPoint, shape: str) -> dict[str, float]:
    """The search coordinates ``shape`` holds at the reference temperature's values
    (:mod:`.shape_choices`): none, the CPE orders, or the orders and the time-constant ratio."""
    if shape == "each":
        return {}
    x = dict(zip(BASE_NAMES, encode_point(reference)))
    keys = ("m", "n") + (("ln_tau_ratio",) if shape == "orders-ratio" else ())
    return {k: float(x[k]) for k in keys}


def on_2rc_submodel(point: ParameterPoint) -> bool:
    """True when a fitted point is the textbook 2-RC model in the fractional form: both CPE
    orders at 1 (within :data:`ORDER_ONE_TOL`) and the Butler–Volmer term linear (not fitted,
    or its exchange current at the largest the search allows, :data:`LINEAR_I0_A`)."""
    return point.m >= 1.0 - ORDER_ONE_TOL and point.n >= 1.0 - ORDER_ONE_TOL and kinetics_linear(point)


def kinetics_linear(point: ParameterPoint) -> bool:
    """True when a point's Butler–Volmer term is linear: not fitted, or its exchange current at the
    largest the search allows (:data:`LINEAR_I0_A`, within :data:`ORDER_ONE_TOL`)."""
    return point.i0_a is None or point.i0_a >= (1.0 - ORDER_ONE_TOL) * LINEAR_I0_A


def ecm_start_point(fit: Ecm2RcFit | Ecm2RcPoint, temp_c: float, linear_kinetics: bool = False,
                    max_tau_df_s: float | None = None) -> ParameterPoint:
    """The fractional model's point that is the textbook 2-RC model (orders 1, ``C = τ/R``):
    where the fractional search starts, so it begins at the bar it has to clear.

    ``linear_kinetics``: for a fit with the Butler–Volmer term, the start carries the largest
    exchange current of the search (:data:`LINEAR_I0_A`), where the term is practically linear
    and the point is still the 2-RC model.  ``max_tau_df_s``: the diffusion branch's time constant
    is capped as the search caps it (:func:`service.cell.fitting.diffusion_tau`), so a profile
    that keeps this point keeps the cap ``socd fit --max-tau-df`` set; below τ2 the point is then
    that much off the 2-RC model, and its RMSE is measured as it is."""
    r1, r2 = max(fit.r1, 1e-5), max(fit.r2, 1e-5)
    tau2 = max(fit.tau2_s, 3.0 * fit.tau1_s)
    tau2 = tau2 if max_tau_df_s is None else min(tau2, max_tau_df_s)  # as diffusion_tau caps the search's
    i0 = LINEAR_I0_A if linear_kinetics else None
    return ParameterPoint(temp_c=temp_c, r_ohm=max(fit.r0, 1e-4), r_ct=r1, c_dl=fit.tau1_s / r1, m=1.0,
                          r_df=r2, c_df=tau2 / r2, n=1.0, i0_a=i0)


def segments_rmse_mv(template: CellProfile, point: ParameterPoint, hysteresis: HysteresisSpec,
                     segments: list[FitSegment], memory_length: int, ea_j_mol: float | None = None) -> float:
    """RMSE [mV] of the fractional model with ``point`` over whole ``segments``; with ``ea_j_mol``,
    scaled from the point's temperature along the recorded one as it was fitted
    (:mod:`service.cell.temperature_law`)."""
    prof = one_point_profile(template, point, hysteresis)
    sq, n = 0.0, 0
    for s in segments:
        u_h0 = s.u_h0 + s.u_h0_branch * hysteresis.u_h_max_v
        params = prof.parameters_at(float(s.temperature_c[0]), n_cells=1)
        law = None
        if ea_j_mol is not None:
            def law(t: float, params=params) -> CellParameters:
                return scaled_by_law(params, temperature_law_factor(ea_j_mol, np.array([t]), point.temp_c))
        v, _ = simulate_batch(prof, s.time_s, s.current_a, s.temperature_c, np.array([s.soc0]), params,
                              memory_length=memory_length, u_h0=u_h0, params_at=law, temp_update_k=LAW_UPDATE_K)
        err = v[:, 0] - s.voltage_v
        sq += float(np.sum(np.where(np.isfinite(err), err, 10.0) ** 2))
        n += err.size
    return 1000.0 * float(np.sqrt(sq / max(n, 1)))


def overpotential_rms_mv(profile: CellProfile, segments: list[FitSegment]) -> float:
    """RMS [mV] of the measured voltage minus the profile's OCV at the SOC counted through each
    segment: the part of the voltage the model's dynamics have to explain."""
    table = profile.ocv_table()
    cap = profile.effective_capacity_ah
    sq, n = 0.0, 0
    for s in segments:
        soc = coulomb_soc(s.time_s, s.current_a, cap, s.soc0)
        eta = s.voltage_v - table.ocv(soc, s.temperature_c)
        sq += float(np.sum(eta**2))
        n += eta.size
    return 1000.0 * float(np.sqrt(sq / max(n, 1)))


def say_rest_alignment(rep: FitReport, temp_c: float, grid: np.ndarray, base_ocv: np.ndarray,
                       points: list[RestPoint], capacity_ah: float) -> None:
    """Report how an OCV table or test was put through a temperature's relaxed rest voltages; a
    notice where the SOC alignment ended on its bound."""
    alignment = rest_alignment(grid, base_ocv, points)
    if alignment is None:
        rep.say(f"OCV at {temp_c:g} °C: shifted to {len(points)} relaxed rest voltages")
        return
    shift, scale = alignment
    rep.say(f"OCV at {temp_c:g} °C: SOC scale aligned to {len(points)} relaxed rest voltages (between them the "
            f"OCV curve's SOC moves as if the cell held {capacity_ah / scale:.3f} Ah, against --capacity-ah "
            f"{capacity_ah:g}; its full point {shift:+.3f}), then shifted to them")
    if alignment_at_bound(alignment):
        rep.say(f"  {temp_c:g} °C: the alignment is at its bound: check --capacity-ah and the full-charge point",
                notice=True)


def check_fit_quality(report: FitReport) -> None:
    """Raise :class:`PoorFitError` naming every temperature whose fit must not be used."""
    bad = [(t, why) for t in report.temperatures if (why := t.problem()) is not None]
    if not bad:
        return
    what = "; ".join(f"{t.temp_c:g} °C: {why}. Data that would help there: {t.data_hint()}" for t, why in bad)
    raise PoorFitError(what)
