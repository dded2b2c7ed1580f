"""Markdown tables from ``socd evaluate --json`` files (the README's results come from here).

    python -m service.evaluation.summary out/eval_pan25.json [more.json ...]

One row per recording, one column per estimator: SOC RMSE after 600 s in percent (the
figure of DESIGN §7), then a row of means, then voltage RMSE means.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

ORDER = ["fomiukf", "foukf", "fom-single-scale", "ecm2rc-ekf", "huwang-rls", "coulomb"]


def table(path: Path) -> str:
    results = json.loads(path.read_text())["results"]
    ests = [e for e in ORDER if any(r["estimator"] == e for r in results)]
    by = defaultdict(dict)
    for r in results:
        by[r["recording"]][r["estimator"]] = r
    lines = [f"`{path.name}`: SOC RMSE after 600 s [%] (voltage RMSE mean in the last row)", "",
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
    lines.append("| V RMSE mean [mV] | " + " | ".join(f"{sum(vs[e]) / len(vs[e]):.1f}" if vs[e] else "-" for e in ests) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    paths = [Path(p) for p in (argv if argv is not None else sys.argv[1:])]
    if not paths:
        print(__doc__)
        return 2
    print("\n\n".join(table(p) for p in paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
