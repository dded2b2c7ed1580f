"""``socd bench``: throughput of the full pipeline, vectorised across a pack vs a per-cell loop;
``socd bench --latency``: frame-to-Zenoh latency of the running service
(:mod:`service.commands.bench_latency`); ``socd bench --simulate``: the offline model simulation
of ``socd fit`` and ``socd diagnose`` (:mod:`service.commands.bench_simulate`)."""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from service.cli import UserError
from service.commands.bench_drive import pack_drive
from service.commands.common_args import (
    add_cell_argument,
    add_common_arguments,
    float_in,
    int_range,
    refuse_overwriting_inputs,
    setup_logging,
    text_stream,
    write_json,
)


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "bench",
        help="cell-steps per second of the full pipeline on one core (pack-vectorised vs per-cell loop)",
        description=(
            "Measure cell-steps/s of the full pipeline (FO-MI-UKF + fast and slow identifiers, default "
            "settings) for a pack of --cells cells on one core, and of the same code run as a plain "
            "per-cell loop (one single-cell estimator per cell) as the reference. The process is pinned "
            "to one CPU. Inputs are a simulated drive (1 s steps) so the numbers do not depend on files."
        ),
    )
    p.add_argument("--cells", type=int_range(1, 100_000), default=None,
                   help="cells in the pack (default 200); --simulate: parameter candidates (default 20)")
    p.add_argument("--steps", type=int_range(10, 10**6), default=None,
                   help="time steps for the pack run (default 400; --simulate: 10000)")
    p.add_argument("--reference-steps", type=int_range(2, 10**5), default=None,
                   help="time steps for the per-cell loop (default 40; --simulate: stepping the model, 1000)")
    p.add_argument("--latency", action="store_true",
                   help="instead: run the service (virtual CAN bus in, Zenoh on tcp/127.0.0.1 out) in real time and "
                        "report frame-to-Zenoh-put and frame-to-subscriber p50/p99")
    p.add_argument("--rate-hz", type=float_in(0.01, 1000.0, "a rate in Hz"), default=10.0, help="--latency: samples per second (default 10)")
    p.add_argument("--seconds", type=float_in(0.1, 86400.0, "a duration in s"), default=60.0,
                   help="--latency: seconds measured, after the warm-up (default 60)")
    p.add_argument("--warmup", type=float_in(0.0, 3600.0, "a duration in s"), default=5.0, metavar="S",
                   help="--latency: seconds run before measuring (default 5)")
    p.add_argument("--simulate", action="store_true",
                   help="instead: candidate-samples/s of the model simulated along a recording, as socd fit and "
                        "socd diagnose run it (needs the [fit] extra), against stepping the model one sample "
                        "at a time on the same inputs, and the largest voltage difference of the two")
    add_cell_argument(p, help="cell profile (default: the bundled Panasonic 18650PF)")
    add_common_arguments(p, json_out="the results")
    p.set_defaults(func=run)


def _inputs(n_cells: int, steps: int, profile, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pack drive of 1 s samples, the current held 10 s at a time (:func:`pack_drive`)."""
    current, volts = pack_drive(profile, n_cells, steps, 1.0, hold=10, seed=seed)
    return current, volts, np.full(n_cells, 25.0)


def run(args: argparse.Namespace) -> int:
    from service.cell.profile import ProfileError, load_profile
    from service.config import DEFAULT_CELL_PROFILE
    from service.estimators.pipeline import PackEstimator
    from service.estimators.settings import EstimatorSettings

    setup_logging(args)
    refuse_overwriting_inputs(args.json, [args.cell or DEFAULT_CELL_PROFILE], "--json")
    if args.latency and args.simulate:
        raise UserError("--latency and --simulate are two different measurements: give one")
    defaults = (20, 10_000, 1_000) if args.simulate else (200, 400, 40)
    args.cells, args.steps, args.reference_steps = (
        given if given is not None else default
        for given, default in zip((args.cells, args.steps, args.reference_steps), defaults))
    try:
        profile = load_profile(args.cell or DEFAULT_CELL_PROFILE)
    except ProfileError as exc:
        raise UserError(str(exc)) from exc
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    if args.latency:
        return _latency(args)
    if args.simulate:
        return _simulate(args, profile)
    from service.estimators.pipeline import PAPER_INNOVATION_LENGTH

    # the paper's full pipeline: multi-innovation window on (heavier than the service default)
    settings = EstimatorSettings(innovation_length=PAPER_INNOVATION_LENGTH)
    n = args.cells
    current, volts, temp = _inputs(n, max(args.steps, args.reference_steps), profile)

    def pack_run(steps: int) -> float:
        est = PackEstimator(profile, n, settings)
        est.initialise(volts[0], temp)
        t0 = time.perf_counter()
        for k in range(steps):
            est.step(1.0, current[k], volts[k], temp)
            est.slow_update()
        return time.perf_counter() - t0

    def loop_run(steps: int) -> float:
        ests = [PackEstimator(profile, 1, settings) for _ in range(n)]
        for c, e in enumerate(ests):
            e.initialise(volts[0, c:c + 1], temp[c:c + 1])
        t0 = time.perf_counter()
        for k in range(steps):
            for c, e in enumerate(ests):
                e.step(1.0, current[k], volts[k, c:c + 1], temp[c:c + 1])
                e.slow_update()
        return time.perf_counter() - t0

    pack_run(5)  # warm-up
    pack_s = min(pack_run(args.steps) for _ in range(3))
    ref_s = loop_run(args.reference_steps)
    result = {
        "cell_steps_per_s": n * args.steps / pack_s,
        "reference_cell_steps_per_s": n * args.reference_steps / ref_s,
        "cells": n,
        "memory_length": settings.memory_length,
        "innovation_length": settings.innovation_length,
        "us_per_pack_step": 1e6 * pack_s / args.steps,
    }
    result["ratio"] = result["cell_steps_per_s"] / result["reference_cell_steps_per_s"]
    out = text_stream(args)
    print(f"pack of {n} cells, L={settings.memory_length}, p={settings.innovation_length}, one core", file=out)
    print(f"  vectorised pipeline : {result['cell_steps_per_s']:12,.0f} cell-steps/s  ({result['us_per_pack_step']:.0f} µs per pack step)", file=out)
    print(f"  per-cell loop (ref.): {result['reference_cell_steps_per_s']:12,.0f} cell-steps/s", file=out)
    print(f"  ratio               : {result['ratio']:12.1f} x", file=out)
    write_json(args.json, result)
    return 0


def _latency(args: argparse.Namespace) -> int:
    from service.commands.bench_latency import result_text, run_latency

    if args.cells > 256:
        raise UserError(f"--latency: --cells must be ≤ 256 (the output frames' cell index), not {args.cells}")
    result = run_latency(args.cells, args.rate_hz, args.seconds, args.warmup, profile_path=args.cell)
    print(result_text(result), file=text_stream(args))
    write_json(args.json, result.to_json())
    return 0


def _simulate(args: argparse.Namespace, profile) -> int:
    from service.commands.bench_simulate import run_simulate_bench

    result = run_simulate_bench(profile, args.cells, args.steps, args.reference_steps)
    print(result.text(), file=text_stream(args))
    write_json(args.json, result.to_json())
    return 0
