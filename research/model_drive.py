"""A recording's current and temperature driven through a cell profile's own model.

``python -m research.model_drive RECORDING -o OUT.csv [--cell PROFILE] [--soc0 1.0] [--noise-v 0.002]``
writes ``time_s,current_a,voltage_v,temperature_c,soc_true``: the recorded current and
temperature, the voltage the profile's model gives along them
(:func:`service.cell.trajectory.simulate`, parameters following the temperature) plus seeded
Gaussian noise, and the model's SOC as the truth.  The recording is consistent with the profile
by construction, so a run of ``socd demo --recording OUT.csv`` on it separates what an estimator
does from how far the profile is from the real cell (docs/results/bench.md, online capacity).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from service.cell.profile import ProfileError, load_profile
from service.cell.trajectory import simulate
from service.config import DEFAULT_CELL_PROFILE
from service.errors import UserError
from service.recording import load_recording, save_recording


def model_drive(recording_path: Path, profile_path: Path, soc0: float, noise_v: float, seed: int) -> np.ndarray:
    """``[T, 5]`` columns of the recording driven through the profile's model (see the module)."""
    profile = load_profile(profile_path)
    rec = load_recording(recording_path)
    v, soc = simulate(profile, rec.time_s, rec.current_a, rec.temperature_c, soc0)
    v = v + np.random.default_rng(seed).normal(0.0, noise_v, v.size)
    return np.column_stack([rec.time_s, rec.current_a, v, rec.temperature_c, soc])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.model_drive", description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", help="recording CSV whose current and temperature drive the model")
    ap.add_argument("-o", "--output", required=True, help="recording CSV to write (with soc_true)")
    ap.add_argument("--cell", default=str(DEFAULT_CELL_PROFILE), help="cell profile (default: the bundled one)")
    ap.add_argument("--soc0", type=float, default=1.0, help="SOC at the first sample (default 1.0)")
    ap.add_argument("--noise-v", type=float, default=0.002, help="σ of the voltage noise added, V (default 0.002)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the noise (default 0)")
    args = ap.parse_args(argv)
    if not 0.0 <= args.soc0 <= 1.0 or args.noise_v < 0:
        print("model_drive: --soc0 must be in [0, 1] and --noise-v >= 0", file=sys.stderr)
        return 2
    try:
        cols = model_drive(Path(args.recording), Path(args.cell), args.soc0, args.noise_v, args.seed)
    except (ProfileError, UserError, ValueError) as exc:
        print(f"model_drive: {exc}", file=sys.stderr)
        return 2
    save_recording(args.output, cols, fmt="%.6f")
    print(f"wrote {args.output}: {len(cols)} samples, SOC {cols[0, 4]:.3f} -> {cols[-1, 4]:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
