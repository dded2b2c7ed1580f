"""Of several profiles of one cell (e.g. ``socd fit`` on different ``--seed``), pick the one whose
filter reads its own fit files best, and print that profile's held-out results file.

Each candidate is two ``socd evaluate --json`` files: the profile scored on the recordings it was
fitted on, and the same profile scored on held-out recordings. The pick reads only the first, so no
held-out file decides it (DESIGN §7); the second is what the pick is then scored on, beside each
candidate, by ``research.nested_tuning``.

    python -m research.fit_file_pick out/a_s0_fit.json:out/a_s0_held.json out/a_s1_fit.json:out/a_s1_held.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

from research.nested_tuning import METRIC


class PickError(ValueError):
    pass


@dataclass(frozen=True)
class Candidate:
    fit_files_json: Path
    held_out_json: Path


def fit_file_score(path: Path, estimator: str = "fomiukf") -> float:
    """``estimator``'s mean SOC RMSE after 600 s [%] over the recordings of one results file."""
    try:
        results = json.loads(path.read_text())["results"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise PickError(f"{path}: cannot read results: {exc}") from exc
    scores = [r[METRIC] for r in results if r.get("estimator") == estimator and r.get(METRIC) is not None]
    if not scores:
        raise PickError(f"{path}: no {estimator} result with a SOC RMSE after 600 s")
    return statistics.fmean(scores)


def pick(candidates: list[Candidate], estimator: str = "fomiukf") -> Candidate:
    """The candidate whose ``estimator`` reads its fit files best; the first of equals."""
    if not candidates:
        raise PickError("no candidate given")
    return min(candidates, key=lambda c: fit_file_score(c.fit_files_json, estimator))


def parse_candidate(text: str) -> Candidate:
    fit, sep, held = text.partition(":")
    if not sep or not fit or not held:
        raise argparse.ArgumentTypeError(f"{text!r}: expected FIT_FILES_JSON:HELD_OUT_JSON")
    return Candidate(Path(fit), Path(held))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.fit_file_pick", description=__doc__.split("\n\n")[0])
    ap.add_argument("candidates", nargs="+", type=parse_candidate, metavar="FIT_FILES_JSON:HELD_OUT_JSON")
    ap.add_argument("--estimator", default="fomiukf")
    args = ap.parse_args(argv)
    try:
        chosen = pick(args.candidates, args.estimator)
    except PickError as exc:
        print(f"fit_file_pick: {exc}", file=sys.stderr)
        return 2
    print(chosen.held_out_json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
