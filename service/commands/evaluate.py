"""``socd evaluate``: score estimators on recordings with the protocol of DESIGN §7."""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from service.cell.profile import ProfileError, load_profile
from service.cell.truth import capacity_slip, ocv_range_problem, per_recording
from service.cli import UserError
from service.commands.common_args import (
    add_cell_argument,
    add_common_arguments,
    finite_float,
    full_at,
    output_dir,
    progress_enabled,
    recording_file,
    recording_help,
    refuse_overwriting_inputs,
    setup_logging,
    text_stream,
    write_json,
)
from service.commands.progress import open_progress
from service.errors import validation_message
from service.estimators.registry import ESTIMATORS, UnknownEstimator, create
from service.estimators.settings import EstimatorSettings
from service.evaluation.aggregate import summarise, summary_lines
from service.evaluation.run import EstimatorScore, evaluate_recordings
from service.recording import load_recording

DEFAULT_ESTIMATORS = list(ESTIMATORS)
#: the textbook filter every table shows beside the estimators asked for (DESIGN §7)
BAR_ESTIMATOR = "ecm2rc-ekf"


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="score estimators on recordings (SOC RMSE/MAE/max, convergence, voltage RMSE)",
        description=(
            "Run estimators on recordings with a cell profile from 'socd fit' and score them against "
            "truth SOC: the recording's soc_true column, else coulomb counting from a full-charge "
            "point. Estimation starts at that point with the SOC wrong by --init-soc-error. Over several "
            "recordings the table ends with each estimator's mean and worst SOC RMSE after 600 s and the "
            "recordings on which it is below the textbook 2-RC EKF."
        ),
    )
    p.add_argument("recordings", nargs="+", metavar="RECORDING", type=recording_file,
                   help=recording_help("CSV: time_s,current_a,voltage_v,temperature_c[,soc_true]"))
    add_cell_argument(p, required=True)
    p.add_argument("--estimator", action="append", metavar="NAME",
                   help=f"estimator to run (repeatable; default all: {', '.join(DEFAULT_ESTIMATORS)}); "
                        f"'{BAR_ESTIMATOR}' is always added as the bar to beat unless --no-bar")
    p.add_argument("--no-bar", action="store_true",
                   help=f"do not add the textbook 2-RC EKF ('{BAR_ESTIMATOR}', on the profile's own 2-RC "
                        "characterisation) to the estimators asked for")
    p.add_argument("--full-at", action="append", type=full_at, metavar="S",
                   help="time [s] of the full-charge point, or 'auto' to detect the end of the CC-CV charge; "
                        "give once for all recordings or once per recording (default: the file's start)")
    p.add_argument("--init-soc-error", type=_soc_error, default=0.20, metavar="E",
                   help="initial SOC error (default 0.20; subtracted where truth starts above 0.8)")
    p.add_argument("--warm-start", action="store_true",
                   help="drive the estimators' polarisation states (RC/CPE branches, hysteresis) with the "
                        "current recorded before the full point, as a service that had been running would "
                        "have them; SOC still starts wrong. Default: every estimator starts relaxed")
    p.add_argument("--current-bias-c", type=_bias_c, default=0.0, metavar="F",
                   help="add a current-sensor offset of F x 1C (signed, e.g. 0.01) to the current every "
                        "estimator reads; the truth keeps the recorded current. Shows what an estimator "
                        "does with a sensor error the truth does not contain: coulomb counting drifts by F "
                        "per hour, a filter that reads the voltage should not. Default 0")
    p.add_argument("--settings", metavar="TOML",
                   help="a TOML of filter settings to override: the config's [estimator] keys (top level or "
                        "under [estimator]; `socd schema` lists them with their defaults), and an [ecm2rc_ekf] "
                        "table for the 2-RC EKF's tuning (voltage_noise_v, current_noise_c, ...)")
    p.add_argument("--plots", metavar="DIR", type=output_dir, help="write PNG plots per recording")
    p.add_argument("--traces", metavar="DIR", type=output_dir,
                   help="write <recording>_traces.csv per recording: time, truth, measured voltage and each "
                        "estimator's SOC and predicted voltage over the scored part (to look into a figure)")
    add_common_arguments(p, progress=True, json_out="the results", bounds=True)
    p.set_defaults(func=run)


def _soc_error(text: str) -> float:
    x = finite_float(text)
    if not 0.0 <= x < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {text}")
    return x


def _bias_c(text: str) -> float:
    x = finite_float(text)
    if abs(x) > 0.5:
        raise argparse.ArgumentTypeError(f"must be a fraction of 1C within ±0.5, got {text}")
    return x


def load_settings(path: str | None) -> tuple[EstimatorSettings, dict]:
    """The pipeline's settings (top level or ``[estimator]``) and the 2-RC EKF's tuning (the
    ``[ecm2rc_ekf]`` table, EkfTuning fields; empty when absent) from one settings file."""
    if path is None:
        return EstimatorSettings(), {}
    import tomllib

    from service.estimators.ecm2rc_ekf import EkfTuning
    from service.validation import InputFileError, read_text

    try:
        raw = tomllib.loads(read_text(path, "settings"))
    except InputFileError as exc:
        raise UserError(str(exc)) from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: cannot read settings: {exc}") from exc
    ekf = raw.pop("ecm2rc_ekf", {})
    if not isinstance(ekf, dict):
        raise UserError(f"{path}: 'ecm2rc_ekf' must be a table of EKF tuning options, got {ekf!r}")
    known = [f.name for f in fields(EkfTuning)]
    for key, value in ekf.items():  # checked here, whether or not the EKF runs, before the long work
        if key not in known:
            raise UserError(f"{path}: field 'ecm2rc_ekf.{key}' is not an EKF tuning option; known: {', '.join(known)}")
        if not isinstance(value, (int, float, str)) or isinstance(value, bool):
            raise UserError(f"{path}: field 'ecm2rc_ekf.{key}': expected a number or a string, got {value!r}")
    if "estimator" in raw and len(raw) > 1:
        # with an [estimator] table the top level holds nothing else: a key beside it would be dropped
        others = ", ".join(sorted(k for k in raw if k != "estimator"))
        raise UserError(f"{path}: {others} beside the [estimator] table would be ignored; put pipeline settings "
                        "under [estimator] (or all at the top level) and the 2-RC EKF's under [ecm2rc_ekf]")
    try:
        EkfTuning(**ekf)
    except ValidationError as exc:
        raise settings_error(path, exc, "ecm2rc_ekf") from exc
    try:
        return EstimatorSettings.model_validate(raw.get("estimator", raw)), ekf
    except ValidationError as exc:
        raise settings_error(path, exc) from exc


def settings_error(path: str, exc: ValidationError, table: str | None = None) -> UserError:
    """One line for a settings file's first invalid field (``table``: the TOML table it sits in), as
    a cell profile's are named (:func:`service.cell.profile.load_profile`)."""
    err = exc.errors()[0]
    field = ".".join(map(str, ([table] if table else []) + list(err["loc"])))
    return UserError(f"{path}: {f'field {field!r}: ' if field else ''}{validation_message(err)}")


def run(args: argparse.Namespace) -> int:
    setup_logging(args)
    try:
        profile = load_profile(args.cell)
    except ProfileError as exc:
        raise UserError(str(exc)) from exc
    if not math.isfinite(args.current_bias_c) or abs(args.current_bias_c) > 0.5:
        raise UserError(f"--current-bias-c must be a finite fraction of 1C within ±0.5, got {args.current_bias_c}")
    if not 0.0 <= args.init_soc_error < 1.0:
        raise UserError(f"--init-soc-error must be in [0, 1), got {args.init_soc_error}")
    names = list(dict.fromkeys(args.estimator or DEFAULT_ESTIMATORS))
    if not args.no_bar and BAR_ESTIMATOR not in names:
        names.append(BAR_ESTIMATOR)
    settings, ekf_tuning = load_settings(args.settings)
    try:
        estimators = [create(n, settings, ekf_tuning if n == "ecm2rc-ekf" else None) for n in names]
    except UnknownEstimator as exc:
        raise UserError(str(exc)) from exc
    full = per_recording(args.full_at, len(args.recordings), "--full-at")
    refuse_overwriting_inputs(args.json, [*args.recordings, args.cell, args.settings], "--json")
    recordings = [load_recording(p) for p in args.recordings]  # validate all before the long work
    table = profile.ocv_table()
    for rec in recordings:
        if (beyond := profile.temperatures_beyond_fit(rec.temperature_c)) is not None:
            print(f"socd evaluate: warning: {rec.path.name}: {beyond}", file=sys.stderr)
        if (slip := capacity_slip(rec, table, profile.effective_capacity_ah, "the profile's capacity_ah")) is not None:
            print(f"socd evaluate: warning: {slip}", file=sys.stderr)
        # a warning, not a refusal as in diagnose: scoring a filter on a profile of another cell is a
        # question a user may mean to ask, but the answer should say what it is
        if (off := ocv_range_problem(rec, table, f"the profile {profile.name!r}")) is not None:
            print(f"socd evaluate: warning: {off}", file=sys.stderr)
    names_seen = [r.name for r in recordings]
    if (args.traces or args.plots) and len(set(names_seen)) < len(names_seen):
        twice = next(n for n in names_seen if names_seen.count(n) > 1)
        raise UserError(f"two recordings are named {twice}: their --traces / --plots files would overwrite "
                        "each other; rename one, or run them apart")
    if args.traces:
        for rec in recordings:
            refuse_overwriting_inputs(Path(args.traces) / f"{rec.name}_traces.csv",
                                      [*args.recordings, args.cell, args.settings], "--traces")
    results: list[EstimatorScore] = []
    total = sum(len(r) for r in recordings) * len(estimators)
    bar = open_progress(progress_enabled(args), "evaluate", total, unit="samples")
    pending = [0]

    def progress(recording: str, estimator: str, samples: int) -> None:
        bar.advance(pending[0])  # the run before this one has finished
        pending[0] = samples
        bar.update(description=f"{recording[:28]}: {estimator}")

    runs = evaluate_recordings(recordings, profile, estimators, full_at=full, init_soc_error=args.init_soc_error,
                               warm_start=args.warm_start, current_bias_c=args.current_bias_c, progress=progress)
    for ev in runs:
        results += ev.scores
        name, part = ev.recording.name, ev.part
        if args.traces:
            write_traces(Path(args.traces) / f"{name}_traces.csv", part.time_s, ev.truth, part.voltage_v, ev.traces)
        if args.plots:
            from service.evaluation.plots import plot_recording

            plot_recording(Path(args.plots), name, part.time_s, ev.truth, part.voltage_v, ev.traces)
    bar.advance(pending[0])
    bar.close()
    summaries = summarise(results, BAR_ESTIMATOR)  # compared only where the bar ran (--no-bar: none)
    out = text_stream(args)
    print_table(results, out)
    if len(recordings) > 1:
        print("\n".join(summary_lines(summaries, BAR_ESTIMATOR)), file=out)
    write_json(args.json, {"results": [asdict(r) for r in results],
                           "summary": [asdict(s) for s in summaries], "cell": str(args.cell),
                           "init_soc_error": args.init_soc_error, "warm_start": bool(args.warm_start),
                           "current_bias_c": args.current_bias_c, "settings": args.settings})
    return 0


def write_traces(path: Path, time_s: np.ndarray, truth: np.ndarray, voltage_v: np.ndarray, traces: dict) -> None:
    """One CSV row per scored sample: ``time_s, soc_true, voltage_v`` then ``soc_<estimator>`` and
    ``v_pred_<estimator>`` (empty where an estimator predicts no voltage, e.g. coulomb counting),
    and ``current_bias_a_<estimator>`` for a filter that learns the sensor offset."""
    cols = {"time_s": time_s, "soc_true": truth, "voltage_v": voltage_v}
    for name, tr in traces.items():
        cols[f"soc_{name}"] = tr.soc
        cols[f"v_pred_{name}"] = tr.v_pred if tr.v_pred is not None else np.full(time_s.shape, np.nan)
        if "current_bias_a" in tr.params:
            cols[f"current_bias_a_{name}"] = tr.params["current_bias_a"]
    path.parent.mkdir(parents=True, exist_ok=True)
    data = np.column_stack(list(cols.values()))
    digits = [12] + [7] * (data.shape[1] - 1)  # time to the recording's own precision
    with path.open("w") as f:
        f.write(",".join(cols) + "\n")
        for row in data:
            f.write(",".join("" if not np.isfinite(v) else f"{v:.{d}g}" for v, d in zip(row, digits)) + "\n")


def _fmt(v: float | None, spec: str) -> str:
    """``v`` formatted by ``spec``; ``-`` in the same width where there is no value."""
    return format("-", f">{spec.split('.')[0]}") if v is None else format(v, spec)


def print_table(results: list[EstimatorScore], out=None) -> None:
    out = out or sys.stdout
    head = (f"{'recording':34s} {'estimator':17s} {'RMSE%':>6s} {'MAE%':>6s} {'max%':>6s} {'RMSE>600s%':>10s} "
            f"{'in 2σ%':>6s} {'conv s':>7s} {'V mV':>6s} {'us/step':>8s}")
    print(head, file=out)
    print("-" * len(head), file=out)
    for r in results:
        print(f"{r.recording[:34]:34s} {r.estimator:17s} {r.soc_rmse_pct:6.2f} {r.soc_mae_pct:6.2f} "
              f"{r.soc_max_pct:6.2f} {_fmt(r.soc_rmse_after_600s_pct, '10.2f')} {_fmt(r.soc_within_2sigma_pct, '6.0f')} "
              f"{_fmt(r.convergence_s, '7.0f')} "
              f"{_fmt(r.v_rmse_mv, '6.1f')} {r.us_per_step:8.1f}", file=out)
