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

from service.cell.profile import CellProfile, ProfileError, load_profile, save_profile
from service.characterisation.two_rc_profile import with_two_rc_points


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
