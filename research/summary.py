"""Markdown tables from ``socd evaluate --json`` files (the tables in docs/results/).

    python -m research.summary out/eval_pan25.json [more.json ...]
    python -m research.summary out/eval_pan25.json+out/eval_pan25_nokin.json
    python -m research.summary --only fomiukf,ecm2rc-ekf out/eval_calce_slow.json+out/eval_calce.json

One row per recording, one column per estimator: SOC RMSE after 600 s in percent (the
figure of DESIGN §7), then a row of means, each estimator's mean difference from the bar
(``ecm2rc-ekf``) with its standard error, paired by recording, and voltage RMSE means.
``A.json+B.json`` puts B's estimators beside A's in one table, each labelled with B's cell
profile (the same estimator scored with another profile); each is compared with the bar
scored with its own profile.  ``--only A,B`` keeps those estimators' columns
(from every file).
"""

from __future__ import annotations

import json
import math
import statistics
import sys
from collections import defaultdict
from pathlib import Path

ORDER = ["fomiukf", "foukf", "fom-single-scale", "ecm2rc-ekf", "huwang-rls", "coulomb"]
#: the estimator every other is compared with (``socd evaluate``'s bar)
BAR = "ecm2rc-ekf"


def paired_difference(pairs: list[tuple[float, float]]) -> tuple[float, float]:
    """Mean of ``a - b`` over ``(a, b)`` pairs (one per recording) and its standard error
    ``sd / sqrt(n)`` (0 for a single pair)."""
    d = [a - b for a, b in pairs]
    se = statistics.stdev(d) / math.sqrt(len(d)) if len(d) > 1 else 0.0
    return statistics.fmean(d), se


def paired_cell(pairs: list[tuple[float, float]]) -> str:
    """``+0.04 ± 0.03`` for :func:`paired_difference` of ``pairs``; ``-`` without a pair."""
    if not pairs:
        return "-"
    diff, se = paired_difference(pairs)
    return f"{diff:+.2f} ± {se:.2f}"


def _results(path: Path, label: bool, only: set[str] | None = None) -> list[dict]:
    doc = json.loads(path.read_text())
    results = [r for r in doc["results"] if only is None or r["estimator"] in only]
    if label:
        tag = Path(str(doc.get("cell", path.stem))).stem
        results = [dict(r, estimator=f"{r['estimator']} ({tag})") for r in results]
    return results


def table(spec: str, only: set[str] | None = None) -> str:
    parts = [Path(p) for p in spec.split("+")]
    results = [r for i, p in enumerate(parts) for r in _results(p, label=i > 0, only=only)]
    named = [r["estimator"] for r in results]
    ests = [e for e in ORDER if e in named] + [e for e in dict.fromkeys(named) if e not in ORDER]
    by = defaultdict(dict)
    for r in results:
        by[r["recording"]][r["estimator"]] = r
    lines = [f"`{'` + `'.join(p.name for p in parts)}`: SOC RMSE after 600 s [%] (voltage RMSE mean in the last row)", "",
             "| recording | " + " | ".join(ests) + " |", "|---" * (len(ests) + 1) + "|"]
    sums = defaultdict(list)
    vs = defaultdict(list)
    for rec, row in by.items():
        cells = []
        for e in ests:
            v = row.get(e, {}).get("soc_rmse_after_600s_pct")
            cells.append("-" if v is None else f"{v:.2f}")
            if v is not None:
                sums[e].append(v)
            mv = row.get(e, {}).get("v_rmse_mv")
            if mv is not None:
                vs[e].append(mv)
        lines.append(f"| {rec} | " + " | ".join(cells) + " |")
    lines.append("| **mean** | " + " | ".join(f"**{sum(sums[e]) / len(sums[e]):.2f}**" if sums[e] else "-" for e in ests) + " |")
    bars = {e: _bar_of(e, ests) for e in ests}
    if any(b is not None for b in bars.values()):
        lines.append(f"| Δ vs {BAR} ± SE | " + " | ".join(
            "-" if bars[e] is None else paired_cell(bar_pairs(by, e, bars[e])) for e in ests) + " |")
    lines.append("| V RMSE mean [mV] | " + " | ".join(f"{sum(vs[e]) / len(vs[e]):.1f}" if vs[e] else "-" for e in ests) + " |")
    return "\n".join(lines)


def _bar_of(estimator: str, ests: list[str]) -> str | None:
    """The bar column an estimator's column is compared with: the bar scored with the same
    profile (``X (tag)`` against ``ecm2rc-ekf (tag)``); None for the bar itself or without one."""
    tag = estimator[estimator.index(" ("):] if " (" in estimator else ""
    bar = BAR + tag
    return bar if bar in ests and bar != estimator else None


def bar_pairs(by: dict[str, dict[str, dict]], a: str, b: str) -> list[tuple[float, float]]:
    """``(a, b)`` SOC RMSE after 600 s per recording where both were scored (``by``: recording →
    estimator → result row)."""
    out = []
    for row in by.values():
        va = row.get(a, {}).get("soc_rmse_after_600s_pct")
        vb = row.get(b, {}).get("soc_rmse_after_600s_pct")
        if va is not None and vb is not None:
            out.append((va, vb))
    return out


def main(argv: list[str] | None = None) -> int:
    specs = list(argv if argv is not None else sys.argv[1:])
    only = None
    if specs[:1] == ["--only"]:
        if len(specs) < 2:
            print("--only needs a comma-separated list of estimators", file=sys.stderr)
            return 2
        only = set(specs[1].split(","))
        specs = specs[2:]
    if not specs:
        print(__doc__)
        return 2
    print("\n\n".join(table(s, only) for s in specs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
