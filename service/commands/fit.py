"""``socd fit``: characterise a cell from recordings and write a cell profile."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import ValidationError

from service.cell.ocv import load_ocv_csv, ocv_table_branch
from service.cell.profile import save_profile
from service.cell.truth import per_recording
from service.characterisation.ocv_choices import (
    NEAR_REFERENCE_K,
    OCV_BETWEEN_RESTS,
    OCV_SMOOTH_WEIGHT,
    REST_INTERP_MAX_GAP,
)
from service.characterisation.profile_pick import (
    DEFAULT_CANDIDATES,
    PICK_ESTIMATOR,
    PICK_LOG_PREFIX,
)
from service.characterisation.shape_choices import DEFAULT_SHAPE, SHAPES
from service.cli import UserError
from service.commands.common_args import (
    PROFILE_SUFFIXES,
    SEED,
    add_common_arguments,
    add_fit_period_argument,
    cpe_order_bound,
    full_at,
    memory_length,
    output_dir,
    output_file,
    positive_float,
    positive_int,
    progress_enabled,
    recording_file,
    recording_help,
    refuse_overwriting_inputs,
    refuse_repeated_inputs,
    refuse_shared_outputs,
    resistance_share,
    setup_logging,
)
from service.commands.progress import open_progress
from service.errors import validation_message
from service.recording import Recording, load_recording

if TYPE_CHECKING:
    import numpy as np

    from service.cell.profile import CellProfile
    from service.characterisation.characterise import FitReport, PoorFitError
    from service.characterisation.fit_summary import FitSummary
    from service.commands.progress import Bar


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "fit",
        help="characterise a cell (OCV, parameters per temperature) and write a cell profile",
        description=(
            "Fit a cell profile from recordings whose SOC is known: an OCV test, HPPC tests or lab drive "
            "cycles that start from a full charge. OCV comes from --ocv, else the OCV tests among the "
            "recordings (each at its own temperature; between tests the OCV is interpolated, beyond them the "
            "nearest test's holds), else a monotone OCV fitted jointly with a textbook 2-RC model; recordings "
            "at several temperatures give OCV(SOC, T) and temperature-dependent parameters (scipy differential "
            "evolution + least squares). Where a temperature's recordings warm or cool the cell by 3 K or more "
            "(a drive cycle in the cold), the resistances' activation energy is fitted with the point, so the "
            "point is the cell at that temperature rather than an average over the span. The textbook 2-RC model (OCV, R0, R1/tau1, R2/tau2 per temperature) is fitted to the "
            "same data and stored beside the fractional one: 'ecm2rc-ekf' runs on it, and a temperature whose "
            "fractional fit is poor or worse than it fails the command (exit 2, nothing written) unless --force. "
            "Where the fractional search ends on the 2-RC model itself (orders 1, no Butler-Volmer bend), the "
            "2-RC fit's own point is kept for that temperature (the fit log says so). The whole fit runs "
            f"{DEFAULT_CANDIDATES} times with different optimiser seeds and the profile whose {PICK_ESTIMATOR} reads "
            "the fit recordings' own SOC best is written (--candidates); where it reads them better with its "
            "reference temperature's point (nearest 25 °C) the textbook 2-RC point, that point is written."
        ),
    )
    p.add_argument("recordings", nargs="+", metavar="RECORDING", type=recording_file,
                   help=recording_help(
                       "CSV: time_s,current_a,voltage_v,temperature_c (OCV tests, pulse tests, drive cycles; "
                       "grouped by the cell's median measured temperature, which a drive that warms the cell "
                       "puts above the ambient)"))
    p.add_argument("--capacity-ah", type=positive_float, required=True, metavar="X", help="cell capacity [Ah]")
    p.add_argument("--full-at", action="append", type=full_at, metavar="S",
                   help="time [s] of the full-charge point ('auto' to detect; once, or once per recording; default: file start)")
    p.add_argument("--ocv", metavar="OCV_CSV", help="OCV table CSV: soc + ocv_v (or ocv_avg_v/...)")
    p.add_argument("--hysteresis", action="store_true", help="also fit the one-state hysteresis (LFP cells)")
    p.add_argument("--ocv-branch", choices=("mean", "charge", "discharge"), default="mean",
                   help="which branch the OCV table or test is: 'mean' (the average of charge and discharge, "
                   "default) or one branch, e.g. 'charge' for an LFP charge curve; the profile records it and "
                   "the model reads the mean as that branch minus/plus U_H (needs --hysteresis)")
    p.add_argument("--kinetics", action=argparse.BooleanOptionalAction, default=None,
                   help="fit a Butler-Volmer exchange current i0 per temperature (the apparent resistance falls as "
                   "the current rises; matters in the cold). Default: at each temperature whose recordings have "
                   "20 or more clean current steps reaching 0.5C (HPPC tests, pulse and DST-like cycles), the "
                   "steps that measure it, unless its i0 ends at the search's lower bound (not measured: that "
                   "temperature is fitted again with linear kinetics); --kinetics fits it at every temperature "
                   "and keeps it, --no-kinetics at none (docs/results/tuning.md)")
    p.add_argument("--min-order", type=cpe_order_bound, default=None, metavar="A",
                   help="lower bound of the CPE orders m, n (default 0.3); the short G-L memory represents low "
                   "orders poorly (the bundled Panasonic profile uses 0.5)")
    p.add_argument("--min-slow-order", type=cpe_order_bound, default=None, metavar="A",
                   help="lower bound of the diffusion branch's CPE order n alone (default: --min-order's); its time "
                   "constant is tens of times the G-L memory, where a low order is mostly truncation")
    p.add_argument("--max-tau-df", type=positive_float, default=None, metavar="S",
                   help="cap on the diffusion branch's time constant, s (default 1000, the textbook 2-RC's slow "
                   "bound; at least 1); a longer one can follow the slow polarisation of a long drive, and can also let "
                   "the branch act as an integrator that soaks up OCV and capacity error")
    p.add_argument("--pure-ohmic-share", type=resistance_share, default=None, metavar="F",
                   help="share of the textbook 2-RC's R0 that R_ohm keeps above the Butler-Volmer term's linear drop "
                   "at each temperature: the electrolyte and contacts conduct ohmically at any current, and in the "
                   "cold a fit can otherwise hand the whole instantaneous drop to the kinetic term (default 0)")
    p.add_argument("--shape", choices=SHAPES, default=DEFAULT_SHAPE,
                   help="which shape of the fractional model the temperatures share: each temperature fitted freely "
                   "(each), the CPE orders m, n of the reference temperature's point held at the others (orders), or "
                   "the orders and the ratio of the two time constants (orders-ratio); with shared orders the profile "
                   f"interpolates the time constants between temperatures (default {DEFAULT_SHAPE}, chosen leave-one-cell-out "
                   "over two optimiser seeds: docs/results/characterisation.md, shape_seeds)")
    p.add_argument("--monotone", action="store_true",
                   help="bound each temperature's R_ohm, R_ct, R_df by the neighbouring fitted temperatures "
                   "(resistance rises in the cold); off by default")
    p.add_argument("--soc-resistance", action="store_true",
                   help="measure how R_ohm and the polarisation resistances change with SOC at each temperature "
                   "from the recordings' discharge pulses from rest (HPPC tests: pulses at five or more SOC levels) "
                   "and fit the parameters with that table in the model; off by default: it fits the HPPC tests 3x closer "
                   "but scores worse for SOC on the Panasonic drive cycles (docs/results/cell_options.md)")
    p.add_argument("--slow-branch", action="store_true",
                   help="add a slow RC branch (time constant of minutes to hours) measured from the voltage recovery "
                   "in rests of 30 min or more at the reference temperature, then fit the rest of the model with it; "
                   "for cells characterised without an OCV test, whose jointly fitted OCV otherwise absorbs the slow "
                   "polarisation (docs/results/cell_options.md: CALCE INR18650-20R)")
    p.add_argument("--short-charge", action="store_true",
                   help="an OCV test whose C/20 charge stopped short of full (it rests below where the discharge "
                   "began, as a cold one does) is counted on the discharge's scale instead of stretched over the "
                   "whole SOC range; reads the OCV closer to the cell's, yet off by default: it scored worse pooled "
                   "over the cells the defaults are chosen on (docs/results/tuning.md)")
    p.add_argument("--ocv-beyond", choices=("hold", "linear"), default="hold",
                   help="with OCV tests at two or more temperatures, the OCV at a temperature beyond them: the "
                   "nearest test's (hold, the default) or the line through the two nearest, their entropic "
                   "slope carried on (linear) (docs/results/characterisation.md)")
    p.add_argument("--rest-anchor", action=argparse.BooleanOptionalAction, default=None,
                   help="with no OCV table or test (the OCV fitted jointly with the model): shift the fitted table at "
                   "each temperature to pass through the voltages that temperature's rests of 600 s or more relax "
                   "towards (each rest's decay extrapolated; the outermost offset holds beyond them; a temperature "
                   "without one keeps its table). Default: on where such a rest exists; --rest-anchor requires one, "
                   "--no-rest-anchor keeps the joint table (docs/results/characterisation.md, tuning.md)")
    p.add_argument("--ocv-between-rests", choices=OCV_BETWEEN_RESTS, default=None,
                   help="with the OCV fitted jointly and anchored at the rests: between two rests at most "
                   f"{REST_INTERP_MAX_GAP:g} apart in SOC (a pulse test's steps), read the OCV as the monotone "
                   f"cubic through the rests at temperatures within {NEAR_REFERENCE_K:g} K of the reference "
                   "(near-reference, the default; the joint shape in the cold), as the joint fit's shape shifted "
                   "onto them (joint), through the rests where the temperature's rests have settled (settled), "
                   "everywhere (interpolate), or as near-reference but in the cold the reference temperature's row "
                   "shifted through that temperature's rests (reference-shape); naming one with an OCV table or test or --no-rest-anchor is an error "
                   "(docs/results/characterisation.md, cell_options.md)")
    p.add_argument("--ocv-smoothing", type=positive_float, default=None, metavar="W",
                   help="with no OCV table or test: the weight of the smoothness penalty on the jointly fitted OCV "
                   f"(default {OCV_SMOOTH_WEIGHT:g}). A larger W gives a smoother table with fewer flat steps where the "
                   "monotone bound holds it up; W = 1 read the Panasonic HPPC-alone drives at 25 °C worse with both filters "
                   "(docs/results/characterisation.md); naming it with an OCV table or test is an error")
    p.add_argument("--max-seconds", type=positive_float, default=60.0, help="optimiser time bound per temperature (default 60); a search usually ends sooner, and the fit log "
                        "says whether the bound cut one (its end point then depends on the machine's load)")
    p.add_argument("--memory-length", type=memory_length, default=16,
                   help="G-L memory length used in the fit, 1-512 samples (default 16)")
    add_fit_period_argument(p, what="the fit")
    p.add_argument("--force", action="store_true",
                   help="write the profile even when a temperature's fit is poor (it leaves more than 50 mV and "
                   "60 %% of the RMS overpotential) or worse than the textbook 2-RC fit of the same data, or when "
                   "--capacity-ah is more than 5 %% above the charge a room-temperature OCV test moved (above 1 %% the "
                   "log gives a notice); without it such a fit exits 2 and writes nothing")
    p.add_argument("--name", default=None, help="profile name (default: the output file's stem)")
    p.add_argument("--starts", type=positive_int, default=1,
                   help="global searches per temperature, seeded --seed, --seed+1, ...; the one that fits the "
                        "recordings best is kept (default 1). The log gives each search's RMSE and the "
                        "polarisation its point predicts after 10 minutes at 1C, and a notice where searches that "
                        "fit alike predict it further apart than the fit's RMSE (pulse tests leave the slow "
                        "branch loosely bound). Costs that many times the fit's run time "
                        "(docs/results/characterisation.md, hppc_seed_spread)")
    p.add_argument("--candidates", type=positive_int, default=DEFAULT_CANDIDATES, metavar="N",
                   help="whole profiles fitted, seeded --seed, --seed+S, --seed+2S, ... (S = --starts, so no two "
                        "searches share a seed); of those the quality check passes, the "
                        f"one whose {PICK_ESTIMATOR} reads the fit recordings' SOC best (all but OCV tests, from a 20 %% "
                        f"wrong start, after 600 s) is written, and the log gives each one's reading (default "
                        f"{DEFAULT_CANDIDATES}, chosen leave-one-cell-out: docs/results/characterisation.md, "
                        "fit_file_pick; 1 fits once and reads nothing). The one kept is read once more with its "
                        "reference temperature's point the textbook 2-RC point, which is written where it reads "
                        "better. Costs N fits plus N + 1 filter runs over the fit recordings. The "
                        "profile's notes keep the readings and the seed kept (notes.profile_pick)")
    p.add_argument("--seed", type=SEED, default=0,
                   help="seed of the global search (default 0); on a cell whose parameters the data pins down poorly, another seed can give as good a fit with other parameters (docs/results/tuning.md)")
    p.add_argument("-o", "--output", required=True, metavar="CELL_FILE", type=output_file(*PROFILE_SUFFIXES), help="profile to write (.toml or .json)")
    p.add_argument("--report", metavar="JSON", type=output_file(".json"),
                   help="also write what the run found as JSON, written only when the profile is: each candidate's "
                   "seed, figures per temperature (fit RMSE, the textbook 2-RC's, the share of the overpotential "
                   "left, the search bounds reached), the quality check's verdict, the pick's SOC reading and "
                   "which candidate the profile is, with its log (service.characterisation.fit_summary)")
    p.add_argument("--plots", metavar="DIR", type=output_dir,
                   help="write PNGs to DIR: each drive or pulse recording with the measured voltage, the fitted "
                   "fractional model and the textbook 2-RC model along it (parameters following the recorded "
                   "temperature) and their residuals, and the profile's OCV(SOC, T); written only when the "
                   "profile is")
    add_common_arguments(p, progress=True, bounds=True)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.characterisation.block_average import describe, to_fit_period
    from service.characterisation.characterise import MIN_TAU_DF_CAP_S

    setup_logging(args)
    refuse_overwriting_inputs(args.output, [*args.recordings, args.ocv], "-o")
    if args.report is not None:
        refuse_overwriting_inputs(args.report, [*args.recordings, args.ocv], "--report")
        if args.report == "-":
            raise UserError(f"--report {args.report}: give a file of its own, apart from the profile (-o)")
        refuse_shared_outputs([("-o", args.output), ("--report", args.report)])
    if not args.capacity_ah > 0:
        raise UserError(f"--capacity-ah must be > 0, got {args.capacity_ah}")
    if args.max_tau_df is not None and args.max_tau_df < MIN_TAU_DF_CAP_S:
        raise UserError(f"--max-tau-df {args.max_tau_df:g}: the cap must be at least {MIN_TAU_DF_CAP_S:g} s, the "
                        "textbook 2-RC's least time constant; a faster diffusion branch is no diffusion branch")
    refuse_repeated_inputs(args.recordings)
    originals = [load_recording(p) for p in args.recordings]
    averaged = to_fit_period(originals, args.fit_period)
    recs = [a.recording for a in averaged]
    full = per_recording(args.full_at, len(recs), "--full-at")
    table = None
    if args.ocv:
        try:
            table = load_ocv_csv(args.ocv)
        except ValueError as exc:
            raise UserError(str(exc)) from exc
    out = Path(args.output)
    bar = open_progress(progress_enabled(args), "fit", None, unit="stages")
    log = fit_report(args, bar)
    if (line := describe(averaged, args.fit_period)) is not None:
        log.say(line)
    if args.ocv and (branch := ocv_table_branch(args.ocv)) is not None and branch != args.ocv_branch:
        log.say(f"{args.ocv}: its only OCV column is the {branch} branch (ocv_{branch}_v), read here as the "
                f"{args.ocv_branch} OCV (--ocv-branch {args.ocv_branch}); --ocv-branch {branch} with --hysteresis "
                "reads it as that branch", notice=True)
    try:
        candidates = [fit_candidate(args, recs, full, table, out.stem, k, bar) for k in range(args.candidates)]
        pick = choose(candidates, originals, full, log, bar)
    except ValidationError as exc:  # the fit's result broke a profile rule: the data did not determine it
        err = exc.errors()[0]
        raise UserError(f"the fit made no valid profile from {', '.join(map(str, args.recordings))}: "
                        f"{'.'.join(map(str, err['loc']))}: {' '.join(validation_message(err).split())}; the recordings do "
                        "not determine it (a drive or rests over more of the SOC range would)") from exc
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    finally:
        bar.close()
    profile = pick.profile
    save_profile(profile, out)
    print(f"wrote {out}: {len(profile.parameters)} temperature(s) "
          f"{', '.join(f'{p.temp_c:g} °C' for p in profile.parameters)}, capacity {profile.capacity_ah:g} Ah")
    if args.report is not None:
        fit_summary(out, candidates, pick).save(Path(args.report))
        print(f"wrote {args.report}: the fit's figures per candidate and temperature")
    if args.plots:
        from service.characterisation.fit_plots import plot_fit

        for plot in plot_fit(profile, recs, full, Path(args.plots)):
            two_rc = "" if plot.two_rc_rmse_mv is None else f", textbook 2-RC {plot.two_rc_rmse_mv:.1f} mV"
            print(f"wrote {plot.path}: fractional {plot.fractional_rmse_mv:.1f} mV{two_rc} RMSE along "
                  f"{plot.recording}")
    return 0


@dataclass(frozen=True)
class Candidate:
    """One profile fitted with optimiser seed ``seed``; ``refusal``: why the quality check refuses it
    (``None`` where it passes, or where ``--force`` writes it anyway)."""

    seed: int
    profile: CellProfile
    refusal: PoorFitError | None
    #: the candidate's fit log and figures per temperature
    report: FitReport


@dataclass(frozen=True)
class Pick:
    """The profile to write, the seed of the candidate it is, and the pick's reading of each candidate
    it scored (seed -> mean SOC RMSE after 600 s on the fit recordings, %; absent: not scored)."""

    profile: CellProfile
    seed: int
    readings: dict[int, float | None]
    #: the kept candidate read with its reference temperature's point the textbook 2-RC point
    #: (None: not read), and whether that is the profile written
    reference_two_rc: float | None = None
    reference_two_rc_written: bool = False


def fit_report(args: argparse.Namespace, bar: Bar) -> FitReport:
    """A fit log that writes above the progress bar (or to stderr) and moves the bar by stage."""
    from service.characterisation.characterise import FitReport

    return FitReport(echo=bar.log if bar.enabled else None, quiet=args.quiet,
                     progress=lambda what, done, total: bar.update(completed=done, total=total, description=what))


def candidate_seed(seed: int, starts: int, k: int) -> int:
    """Candidate ``k``'s first optimiser seed: each candidate runs ``starts`` searches per temperature,
    seeded from here up, so candidates are spaced ``starts`` apart and never share a search."""
    return seed + k * starts


def fit_candidate(args: argparse.Namespace, recs: list[Recording], full: list[str | float | None],
                  table: tuple[np.ndarray, np.ndarray] | None, stem: str, k: int, bar: Bar) -> Candidate:
    """Candidate ``k`` (from 0): the profile fitted with optimiser seed :func:`candidate_seed`, read by
    the quality check."""
    from service.characterisation.characterise import (
        MAX_TAU_DF_S,
        PURE_OHMIC_SHARE,
        PoorFitError,
        characterise,
        check_fit_quality,
    )

    seed = candidate_seed(args.seed, args.starts, k)
    report = fit_report(args, bar)
    if k:  # the first fit's log reads as a single fit's, and its errors come first
        report.say(f"candidate profile {k + 1} of {args.candidates}: the fit again with optimiser seed "
                   f"{seed} (the first used {args.seed})")
    profile, report = characterise(recs, args.capacity_ah, full, table, args.hysteresis,
                                   fit_kinetics=args.kinetics, max_seconds=args.max_seconds,
                                   min_order=args.min_order, min_slow_order=args.min_slow_order, monotone=args.monotone,
                                   soc_resistance=args.soc_resistance, slow_branch=args.slow_branch,
                                   ocv_branch=args.ocv_branch, rest_anchor=args.rest_anchor,
                                   short_charge=args.short_charge, max_tau_df_s=args.max_tau_df or MAX_TAU_DF_S,
                                   pure_ohmic_share=(PURE_OHMIC_SHARE if args.pure_ohmic_share is None
                                                     else args.pure_ohmic_share),
                                   ocv_beyond=args.ocv_beyond, ocv_between_rests=args.ocv_between_rests,
                                   ocv_smoothing=args.ocv_smoothing, memory_length=args.memory_length,
                                   name=args.name or stem, seed=seed, starts=args.starts,
                                   force_capacity=args.force, shape=args.shape, report=report)
    try:
        check_fit_quality(report)
    except PoorFitError as exc:
        if not args.force:
            return Candidate(seed, profile, exc, report)
        print(f"socd fit: warning: --force writes a fit it would refuse: {exc.problems}", file=sys.stderr)
    return Candidate(seed, profile, None, report)


def choose(candidates: list[Candidate], originals: list[Recording], full: list[str | float | None],
           log: FitReport, bar: Bar) -> Pick:
    """Of the candidates the quality check passes, the one whose filter reads the fit recordings
    best (:mod:`service.characterisation.profile_pick`); the first refusal is raised where none passes."""
    from service.characterisation.characterise import reference_temperature
    from service.characterisation.profile_pick import (
        FitFileScore,
        describe_pick,
        describe_reference_two_rc,
        fit_file_score,
        pick_profile,
        reference_two_rc_variant,
        scored_recordings,
    )

    passed = [c for c in candidates if c.refusal is None]
    if not passed:
        raise candidates[0].refusal  # type: ignore[misc]
    if len(candidates) == 1:
        return Pick(passed[0].profile, passed[0].seed, {})
    if refused := [str(c.seed) for c in candidates if c.refusal is not None]:
        log.say(f"{PICK_LOG_PREFIX}the quality check refuses the fit of seed {', '.join(refused)}; picking among the "
                "others", notice=True)
    recs, full_at = scored_recordings(originals, full, passed[0].profile.capacity_ah)
    scored = []
    for c in passed:
        def progress(recording: str, estimator: str, samples: int, seed: int = c.seed) -> None:
            bar.update(description=f"seed {seed}'s {estimator} on {recording[:24]}")

        try:
            scored.append((c.profile, fit_file_score(c.profile, c.seed, recs, full_at, progress)))
        except (ValueError, UserError) as exc:  # a truth the evaluation refuses: the fit itself stands
            what = f"the fit recordings cannot be scored ({exc}); keeping seed {passed[0].seed}'s"
            return Pick(say_pick(passed[0].profile, what, log, notice=True), passed[0].seed, {})
    profile, kept = pick_profile(scored)
    readings = {s.seed: s.soc_rmse_after_600s_pct for _, s in scored}
    what = describe_pick([s for _, s in scored], kept)
    variant = reference_two_rc_variant(profile)
    if variant is None:
        return Pick(say_pick(profile, what, log), kept.seed, readings)
    bar.update(description=f"seed {kept.seed}'s profile with its reference point the 2-RC point")
    try:
        read = fit_file_score(variant, kept.seed, recs, full_at)
    except (ValueError, UserError):  # scored above with the same recordings; kept as a guard
        read = FitFileScore(kept.seed, None, 0)
    ref_t = reference_temperature(p.temp_c for p in profile.parameters)
    # the seeds' rule: the lower reading, the fitted point on equals (the variant reads the same
    # recordings, so it is unscored exactly where the kept profile is)
    chosen, _ = pick_profile([(profile, kept), (variant, read)])
    written = chosen is variant
    what += "; " + describe_reference_two_rc(kept, read, ref_t, written)
    return Pick(say_pick(chosen, what, log), kept.seed, readings, read.soc_rmse_after_600s_pct, written)


def say_pick(profile: CellProfile, what: str, log: FitReport, notice: bool = False) -> CellProfile:
    """Log what the pick did and return ``profile`` with it in its notes (``profile_pick``), so the file
    says which candidate it is and why after the log is gone."""
    log.say(PICK_LOG_PREFIX + what, notice=notice)
    return profile.model_copy(update={"notes": {**profile.notes, "profile_pick": what}})


def fit_summary(out: Path, candidates: list[Candidate], pick: Pick) -> FitSummary:
    """The run as ``--report`` writes it (:mod:`service.characterisation.fit_summary`)."""
    from service.characterisation.fit_summary import (
        CandidateSummary,
        FitSummary,
        TemperatureSummary,
        with_picked_two_rc,
    )

    def summary(c: Candidate) -> CandidateSummary:
        written = c.seed == pick.seed
        picked_two_rc = written and pick.reference_two_rc_written
        temperatures = [TemperatureSummary.of(t) for t in c.report.temperatures]
        return CandidateSummary(seed=c.seed, written=written,
                                refusal=None if c.refusal is None else c.refusal.problems,
                                fit_file_soc_rmse_after_600s_pct=pick.readings.get(c.seed),
                                reference_two_rc_soc_rmse_after_600s_pct=pick.reference_two_rc if written else None,
                                reference_two_rc_written=picked_two_rc,
                                temperatures=with_picked_two_rc(temperatures) if picked_two_rc else temperatures,
                                log=list(c.report.lines))

    return FitSummary(profile=str(out), profile_pick=pick.profile.notes.get("profile_pick"),
                      candidates=[summary(c) for c in candidates])
