"""``socd diagnose``: where model and recording differ, which physics is missing, and the fix.

    socd diagnose RECORDING [--cell CELL_FILE | --ocv OCV_CSV --capacity-ah X]
                  [--json OUT] [--report DIR] [--save-profile OUT]

Prints a summary; ``--json`` writes ``{"verdict", "assessment", "effects": [...], "located": [...], ...}``
(``-`` for stdout), ``--report`` a markdown report with PNG plots, ``--save-profile`` the
cell profile extended with the verdict's physics (the base profile when the verdict is
``none``) for ``socd evaluate`` and the service.

``assessment.state`` reads the verdict: ``named``; ``explained`` (``none``, and the base model
is within 3 x the voltage noise on the held-out part); ``unexplained`` (``none``, but a larger
residual is left that no candidate removes; the candidates that only fit the fit part are listed).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.cli import UserError
from service.commands.common_args import (
    PROFILE_SUFFIXES,
    SEED,
    add_cell_argument,
    add_common_arguments,
    add_fit_period_argument,
    add_soc0_argument,
    float_in,
    json_to_stdout,
    output_dir,
    output_file,
    plain_text,
    positive_float,
    progress_enabled,
    recording_file,
    recording_help,
    refuse_overwriting_inputs,
    refuse_shared_outputs,
    setup_logging,
    write_json,
)
from service.commands.progress import open_progress


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="locate model/recording mismatch, name the missing physics, refit and score it held-out",
        description=plain_text(__doc__.split("\n\n")[0] + "\n\n" + __doc__.split("\n\n")[-1].strip()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", type=recording_file,
                   help=recording_help("recording CSV (time_s,current_a,voltage_v,temperature_c)"))
    src = p.add_mutually_exclusive_group(required=True)
    add_cell_argument(src, help="cell profile (TOML/JSON) to start from")
    src.add_argument("--ocv", help="OCV(SOC) table CSV (soc + ocv_v/ocv_avg_v/...); needs --capacity-ah")
    p.add_argument("--capacity-ah", type=positive_float, help="capacity in Ah (with --ocv)")
    p.add_argument("--report", type=output_dir, help="write report.md and PNG plots into this directory")
    p.add_argument("--save-profile", type=output_file(*PROFILE_SUFFIXES), help="write the extended cell profile here (.json or .toml): the verdict's "
                   "extension, or the base model alone when the verdict is none")
    p.add_argument("--save-effect", metavar="NAME",
                   help="with --save-profile: save this candidate's extension instead of the verdict's, even when "
                   "it is not significant (your call, e.g. from other evidence); 'none' saves the base model")
    p.add_argument("--fit-fraction", type=_fit_fraction, default=0.6, help="share of the duration fitted (default 0.6)")
    p.add_argument("--split", choices=("chronological", "interleaved", "blocks"), default="chronological",
                   help="held-out part: 'chronological' the last 40 %% of the duration (default); 'interleaved' "
                        "blocks 2, 4, 7 and 9 of 10; 'blocks' alternating blocks of about 10 minutes, every "
                        "second one held out")
    add_soc0_argument(p, help="known initial SOC in [0, 1] (default: from the opening rest voltage)")
    p.add_argument("--effects", help="comma-separated subset of candidate effects to try (default: all)")
    p.add_argument("--nominal-ambient-c", type=_ambient, default=25.0, metavar="C",
                   help="the ambient a nominal recording is in (default 25 °C); a recording that opens 5 K or more "
                   "away from it and whose temperature then moves by 2 K or more has its temperature effect "
                   "nominated; 'none' judges the temperature only by how well a constant ambient explains it")
    p.add_argument("--seed", type=SEED, default=0,
                   help="seed of the base model's and each effect's global search (default 0)")
    add_fit_period_argument(p, what="the diagnosis (its rules were chosen on 1 s recordings)")
    add_common_arguments(p, progress=True, json_out="the result", bounds=True)
    p.set_defaults(func=run)


def _ambient(text: str) -> float | None:
    """A temperature in °C (-60..100), or 'none'."""
    if text.strip().lower() == "none":
        return None
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if not -60.0 <= x <= 100.0:
        raise argparse.ArgumentTypeError(f"must be a temperature in °C (-60..100) or 'none', got {text!r}")
    return x


_fit_fraction = float_in(0.2, 0.9, "a fraction of the recording")


def _note(args: argparse.Namespace, message: str) -> None:
    if not args.quiet:
        print(f"socd diagnose: {message}", file=sys.stderr, flush=True)


def _effects_from_arg(text: str, known: tuple[str, ...]) -> tuple[str, ...]:
    """The candidate effects ``--effects`` names, in its order; :class:`UserError` for a list that
    names none, an unknown name, or a name given twice (the second would silently be dropped)."""
    effects = [e.strip() for e in text.split(",") if e.strip()]
    if not effects:
        raise UserError(f"--effects names no effect ({text!r}); choose from {', '.join(known)}, "
                        "or leave the flag out for all")
    bad = list(dict.fromkeys(e for e in effects if e not in known))
    if bad:
        raise UserError(f"--effects: unknown effect(s) {', '.join(bad)}; choose from {', '.join(known)}")
    twice = list(dict.fromkeys(e for e in effects if effects.count(e) > 1))
    if twice:
        raise UserError(f"--effects: {', '.join(twice)} given more than once; name each effect once")
    return tuple(effects)


def _profile_from_args(args):
    from pydantic import ValidationError

    from service.cell.ocv import load_ocv_csv
    from service.cell.profile import ProfileError, load_profile
    from service.config import format_validation_error
    from service.diagnosis.pipeline import table_profile

    if args.cell:
        if args.capacity_ah is not None:
            raise UserError("--capacity-ah goes with --ocv; with --cell the profile's capacity is used "
                            "(edit capacity_ah in the profile to change it)")
        try:
            return load_profile(args.cell), False
        except ProfileError as exc:
            raise UserError(str(exc)) from exc
    if args.capacity_ah is None:
        raise UserError("--ocv needs --capacity-ah (the cell's capacity in Ah)")
    if not args.capacity_ah > 0:
        raise UserError(f"--capacity-ah must be positive, got {args.capacity_ah:g}")
    try:
        soc, ocv = load_ocv_csv(args.ocv)
    except FileNotFoundError as exc:
        raise UserError(f"{args.ocv}: no such OCV table") from exc
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    try:
        profile = table_profile(Path(args.ocv).stem, args.capacity_ah, soc, ocv)
        profile.ocv_table()
    except ValidationError as exc:  # one line, the first problem, as socd check words it
        raise UserError(format_validation_error(exc, f"{args.ocv}: unusable OCV table").splitlines()[0]) from exc
    except ValueError as exc:
        raise UserError(f"{args.ocv}: unusable OCV table: {exc}") from exc
    return profile, True


def run(args: argparse.Namespace) -> int:
    from service.cell.profile import save_profile
    from service.cell.truth import (
        capacity_slip,
        check_counted_span,
        check_current_scale,
        check_current_sign,
        check_ocv_range,
        check_unlogged_charge,
        check_voltage_moves,
    )
    from service.characterisation.block_average import describe, to_fit_period
    from service.diagnosis.effects import EFFECTS
    from service.diagnosis.pipeline import DiagnoseOptions, opens_under_load, run_diagnosis
    from service.recording import load_recording

    setup_logging(args)
    inputs = [args.recording, args.ocv, getattr(args, "cell", None)]
    refuse_overwriting_inputs(args.save_profile, inputs, "--save-profile")
    refuse_overwriting_inputs(args.json, inputs, "--json")
    refuse_shared_outputs([("--json", args.json), ("--save-profile", args.save_profile)])
    profile, fit_base = _profile_from_args(args)
    averaged = to_fit_period([load_recording(args.recording)], args.fit_period)
    rec = averaged[0].recording
    if (line := describe(averaged, args.fit_period)) is not None and not args.quiet:
        print(f"socd diagnose: {line}", file=sys.stderr)
    if not 0.2 <= args.fit_fraction <= 0.9:
        raise UserError(f"--fit-fraction must be in [0.2, 0.9], got {args.fit_fraction:g}")
    effects = tuple(EFFECTS) if args.effects is None else _effects_from_arg(args.effects, tuple(EFFECTS))
    if len(rec) < 100:
        raise UserError(f"{rec.path}: {len(rec)} samples is too short to fit and hold out (need >= 100)")
    check_current_sign(rec)
    check_voltage_moves(rec)
    source = "--capacity-ah" if fit_base else "the profile's capacity_ah"
    check_current_scale(rec, profile.effective_capacity_ah, source)
    check_counted_span(rec, profile.effective_capacity_ah)
    check_unlogged_charge(rec, profile.effective_capacity_ah, source)
    table = profile.ocv_table()
    check_ocv_range(rec, table, f"the OCV table {args.ocv}" if fit_base else f"the profile {args.cell}")
    if (slip := capacity_slip(rec, table, profile.effective_capacity_ah, source)) is not None:
        print(f"socd diagnose: warning: {slip}", file=sys.stderr)
    if not fit_base and (beyond := profile.temperatures_beyond_fit(rec.temperature_c)) is not None:
        print(f"socd diagnose: warning: {rec.path.name}: {beyond}", file=sys.stderr)
    if args.soc0 is not None and not 0.0 <= args.soc0 <= 1.0:
        raise UserError(f"--soc0 must be in [0, 1], got {args.soc0:g}")
    if args.soc0 is None and opens_under_load(rec, profile.effective_capacity_ah):
        print(f"socd diagnose: warning: {rec.path}: it opens under load ({rec.current_a[0]:g} A), not at rest: its "
              "initial SOC is read from the first voltage corrected by R_ohm·I, without the polarisation before it, "
              "and a start SOC a few % off can be named hysteresis, capacity or ocv; give --soc0 if it is known",
              file=sys.stderr)
    if args.save_effect is not None:
        if not args.save_profile:
            raise UserError("--save-effect needs --save-profile (where to write it)")
        if args.save_effect != "none" and args.save_effect not in effects:
            raise UserError(f"--save-effect: '{args.save_effect}' is not among the candidates tried "
                            f"({', '.join(effects)}) or 'none'")
    nominal = args.nominal_ambient_c
    opt = DiagnoseOptions(fit_fraction=args.fit_fraction, split=args.split, soc0=args.soc0, effects=effects,
                          seed=args.seed, fit_base=fit_base, nominal_ambient_c=nominal)
    # one step for the base fit and one per candidate refit: each announced fit ends the one before
    total = 1 + len(effects)
    bar = open_progress(progress_enabled(args), "diagnose", total, unit="fits")
    started = 0

    def say(message: str) -> None:
        nonlocal started, total
        if message.startswith("confirming "):  # a second pass over the nominated effects on another split
            total += 1 + len(message[len("confirming "):].split(" on the ")[0].split(", "))
            bar.update(total=total)
        if message.startswith(("fitting the base model", "refitting with")):
            if started:
                bar.advance(1)
            started += 1
            bar.update(description=message)
        else:
            bar.log(f"socd diagnose: {message}")

    try:
        dg = run_diagnosis(rec, profile, opt, progress=say)
        bar.update(completed=total)
    except ValueError as exc:
        raise UserError(f"{rec.path}: {exc}") from exc
    finally:
        bar.close()
    result = dg.to_json()
    write_json(args.json, result)
    if args.report:
        from service.diagnosis.report import write_report

        path = write_report(dg, args.report)
        _note(args, f"report: {path}")
    if args.save_profile:
        save_profile(dg.best_profile() if args.save_effect is None else dg.profile_of(args.save_effect),
                     args.save_profile)
        _note(args, f"profile: {args.save_profile}")
    if not json_to_stdout(args):
        print(f"verdict: {dg.verdict} ({dg.assessment['state']}: {dg.assessment['text']})")
        for e in dg.effects:
            flag = "*" if e.significant else " "
            print(f" {flag} {e.name:13s} held-out RMSE {e.rmse_before_mv:7.2f} -> {e.rmse_after_mv:7.2f} mV "
                  f"({100 * e.score:+6.1f} %)  dBIC {e.delta_bic:8.1f}")
        print(f"({dg.seconds:.0f} s)")
    return 0
