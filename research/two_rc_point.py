"""A cell profile whose fractional points are its own textbook 2-RC points.

``python -m research.two_rc_point PROFILE OUT [--temp T ...] [--ocv two-rc]`` writes ``PROFILE`` with the
fractional parameter point at each temperature ``T`` (default: every temperature) replaced by the
2-RC point ``socd fit`` stored beside it, written in the fractional form (both CPE orders 1,
``C = τ/R``: :func:`service.characterisation.characterise.ecm_start_point`), and the hysteresis
off. ``fomiukf`` on the result runs the pipeline's filter on the textbook model, which separates
what the fractional fit costs or gains from what the filter does
(docs/results/characterisation.md). ``--ocv two-rc`` also replaces the OCV table by the one the
2-RC fit stored (its joint fit, or the given OCV), so with every temperature replaced the profile
is the textbook EKF's whole model and only the filters differ.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from service.cell.profile import CellProfile, ProfileError, load_profile, save_profile
from service.characterisation.two_rc_profile import SAME_TEMP_C, with_two_rc_points


def with_two_rc_ocv(profile: CellProfile) -> CellProfile:
    """``profile`` with its OCV rows replaced by the 2-RC fit's own rows, read on the profile's SOC
    grid at the profile's temperatures (the 2-RC fit stores a row at each fitted temperature)."""
    if profile.ecm2rc is None:
        raise ValueError(f"profile '{profile.name}' has no 2-RC fit (fit it with a current `socd fit`)")
    own = profile.ecm2rc.ocv
    rows = []
    for t in profile.ocv.temps_c:
        k = next((j for j, te in enumerate(own.temps_c) if abs(te - t) < SAME_TEMP_C), None)
        if k is None:
            raise ValueError(f"profile '{profile.name}': the 2-RC fit has no OCV row at {t:g} °C")
        rows.append(np.interp(profile.ocv.soc, own.soc, own.ocv_v[k]).tolist())
    return profile.model_copy(update={"ocv": profile.ocv.model_copy(update={"ocv_v": rows})})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.two_rc_point", description=__doc__.split("\n\n")[0])
    ap.add_argument("profile", help="cell profile from `socd fit` (TOML/JSON)")
    ap.add_argument("output", help="profile to write")
    ap.add_argument("--temp", type=float, action="append", metavar="T",
                    help="temperature [°C] whose point is replaced (repeatable; default: every one)")
    ap.add_argument("--ocv", choices=("fractional", "two-rc"), default="fractional",
                    help="the OCV table kept: the fractional profile's (default) or the 2-RC fit's own")
    args = ap.parse_args(argv)
    try:
        out = with_two_rc_points(load_profile(args.profile), args.temp)
        if args.ocv == "two-rc":
            out = with_two_rc_ocv(out)
    except (ProfileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    save_profile(CellProfile.model_validate(out.model_dump()), args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
