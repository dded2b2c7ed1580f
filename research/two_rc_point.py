"""A cell profile whose fractional points are its own textbook 2-RC points.

``python -m research.two_rc_point PROFILE OUT [--temp T ...]`` writes ``PROFILE`` with the
fractional parameter point at each temperature ``T`` (default: every temperature) replaced by the
2-RC point ``socd fit`` stored beside it, written in the fractional form (both CPE orders 1,
``C = τ/R``: :func:`service.characterisation.characterise.ecm_start_point`), and the hysteresis
off. ``fomiukf`` on the result runs the pipeline's filter on the textbook model, which separates
what the fractional fit costs or gains from what the filter does
(docs/results/characterisation.md).
"""

from __future__ import annotations

import argparse
import sys

from service.cell.profile import (
    CellProfile,
    HysteresisSpec,
    ParameterPoint,
    ProfileError,
    load_profile,
    save_profile,
)
from service.characterisation.characterise import ecm_start_point

#: temperatures closer than this [°C] are the same point
SAME_TEMP_C = 0.1


def with_two_rc_points(profile: CellProfile, temps_c: list[float] | None = None) -> CellProfile:
    """``profile`` with the fractional point at each of ``temps_c`` (None: all) set to its 2-RC point."""
    if profile.ecm2rc is None:
        raise ValueError(f"profile '{profile.name}' has no 2-RC fit (fit it with a current `socd fit`)")
    ecm_points = profile.ecm2rc.points
    wanted = [e.temp_c for e in ecm_points] if temps_c is None else temps_c
    points: list[ParameterPoint] = []
    replaced = []
    for point in profile.parameters:
        if any(abs(point.temp_c - t) < SAME_TEMP_C for t in wanted):
            ecm = next((e for e in ecm_points if abs(e.temp_c - point.temp_c) < SAME_TEMP_C), None)
            if ecm is None:
                raise ValueError(f"profile '{profile.name}' has no 2-RC point at {point.temp_c:g} °C")
            point = ecm_start_point(ecm, point.temp_c, linear_kinetics=point.i0_a is not None)
            replaced.append(point.temp_c)
        points.append(point)
    missing = [t for t in wanted if not any(abs(t - r) < SAME_TEMP_C for r in replaced)]
    if missing:
        raise ValueError(f"profile '{profile.name}' has no fractional point at {', '.join(f'{t:g}' for t in missing)} °C")
    return profile.model_copy(update={
        "parameters": points,
        "hysteresis": HysteresisSpec(table_branch=profile.hysteresis.table_branch),
    })


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.two_rc_point", description=__doc__.split("\n\n")[0])
    ap.add_argument("profile", help="cell profile from `socd fit` (TOML/JSON)")
    ap.add_argument("output", help="profile to write")
    ap.add_argument("--temp", type=float, action="append", metavar="T",
                    help="temperature [°C] whose point is replaced (repeatable; default: every one)")
    args = ap.parse_args(argv)
    try:
        out = with_two_rc_points(load_profile(args.profile), args.temp)
    except (ProfileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    save_profile(CellProfile.model_validate(out.model_dump()), args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
