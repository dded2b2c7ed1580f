"""Choose a tuning value for each scored file without looking at that file (leave one out).

``socd evaluate`` runs of one estimator over a grid of a setting (one ``--settings`` file per
value) give each recording a score per value.  For every recording this picks the value with
the lowest mean score over the *other* recordings of the same cell (the cell profile named in
the JSON), then reports the recording's score at that value.  So no file is scored with a
value chosen on it (DESIGN §7: never fit on the file being scored), and two estimators swept
over the same grid are tuned with the same care.

    python -m research.nested_tuning --estimator ecm2rc-ekf \\
        1e-4=out/a_1e-4.json 1e-4=out/b_1e-4.json 1e-3=out/a_1e-3.json 1e-3=out/b_1e-3.json
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import re
import statistics
import sys
from collections import defaultdict
from pathlib import Path

from research.summary import paired_difference as paired_difference_of

METRIC = "soc_rmse_after_600s_pct"
#: a default moves only when the pooled gain of the new value over it is larger than this many
#: standard errors of the paired difference (:func:`paired_difference`); a smaller gain is a tie,
#: and a tie keeps the current default (as the diagnosis rules' search does, ``research.devset``)
MOVE_MARGIN_SE = 2.0


class GridError(ValueError):
    pass


@functools.cache
def _read(path: str) -> dict:
    """One results file, parsed once however many estimators are tuned from it."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise GridError(f"{path}: cannot read results: {exc}") from exc


def _condition(doc: dict) -> str:
    """The test condition a results file was run under (its current-sensor offset)."""
    return f"bias {float(doc.get('current_bias_c') or 0.0):+g}C"


def load_grid(pairs: list[str], estimator: str, metric: str = METRIC,
              exclude: str | None = None) -> tuple[list[str], list[str], dict]:
    """``VALUE=JSON[@CELL]`` pairs -> (values, conditions, {cell: {recording: {value: {condition: score}}}}).

    The cell is the profile named in the JSON unless ``@CELL`` names it (two profiles of one
    cell, e.g. characterised from different data, then count as one cell). Under ``@CELL`` the
    k-th file given for a cell at one value and condition is matched with the k-th at every other
    value, so each value may have its own profiles (e.g. fitted with other ``socd fit`` options).

    A condition is what a file was run under (``socd evaluate --current-bias-c``); the same
    recording under several conditions is scored by its mean over them.  Recordings whose name
    matches the regular expression ``exclude`` are left out (scored elsewhere, not tuned for)."""
    values: list[str] = []
    conditions: list[str] = []
    grid: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(dict)))
    files_seen: dict[tuple[str, str, str], int] = defaultdict(int)
    for pair in pairs:
        value, sep, path = pair.partition("=")
        path, _, cell_name = path.partition("@")
        if not sep or not value or not path:
            raise GridError(f"'{pair}': expected VALUE=RESULTS.json[@CELL]")
        doc = _read(path)
        rows = [r for r in doc.get("results", []) if r.get("estimator") == estimator
                and not (exclude and re.search(exclude, str(r.get("recording", ""))))]
        if not rows:
            raise GridError(f"{path}: no results for estimator '{estimator}'")
        cond = _condition(doc)
        values += [value] if value not in values else []
        conditions += [cond] if cond not in conditions else []
        cell = cell_name or str(doc.get("cell", path))
        k = files_seen[(cell, value, cond)]
        files_seen[(cell, value, cond)] += 1
        for r in rows:
            score = r.get(metric)
            if score is None:
                raise GridError(f"{path}: recording {r.get('recording')}: no '{metric}'")
            # under @CELL a recording is named by its file's place: two profiles of one cell score the same files
            rec = f"{cell}#{k + 1}/{r['recording']}" if cell_name else r["recording"]
            grid[cell][rec][value][cond] = float(score)
    for cell, recs in grid.items():
        for rec, by_value in recs.items():
            for v in values:
                missing = [c for c in conditions if c not in by_value.get(v, {})]
                if missing:
                    raise GridError(f"{cell}: {rec} has no result for value {v} under {', '.join(missing)}")
    return values, conditions, grid


def leave_one_out(values: list[str], conditions: list[str], grid: dict) -> list[dict]:
    """One row per recording: the value chosen on the cell's other recordings (mean score over
    them and every condition) and the recording's scores at it.  A cell with a single
    recording has nothing to choose on and is reported unchosen."""
    rows = []
    for cell, recs in grid.items():
        mean = {r: {v: sum(by_value[v].values()) / len(conditions) for v in values} for r, by_value in recs.items()}
        for rec, by_value in recs.items():
            others = [m for r, m in mean.items() if r != rec]
            row = {"cell": cell, "recording": rec, "mean_by_value": mean[rec], "chosen": None, "scores": None}
            if others:
                pooled = {v: sum(o[v] for o in others) / len(others) for v in values}
                chosen = min(values, key=lambda v: (pooled[v], values.index(v)))
                row.update(chosen=chosen, scores=dict(by_value[chosen]))
            rows.append(row)
    return rows


def cell_means(values: list[str], conditions: list[str], grid: dict) -> dict[str, dict[str, dict[str, float]]]:
    """{cell: {value: {condition: mean score over the cell's recordings}}}."""
    out: dict = {}
    for cell, recs in grid.items():
        out[cell] = {v: {c: sum(by_value[v][c] for by_value in recs.values()) / len(recs) for c in conditions}
                     for v in values}
    return out


def leave_one_cell_out(values: list[str], conditions: list[str], grid: dict) -> list[dict]:
    """One row per cell: the value that does best on the *other* cells (each cell weighted
    equally, pooled over every condition) and the held-out cell's scores at it.  This is how
    a default is chosen for cells nobody has seen (DESIGN §7 and the generalisation rule)."""
    means = cell_means(values, conditions, grid)
    pooled = {cell: {v: sum(by_c.values()) / len(conditions) for v, by_c in by_value.items()}
              for cell, by_value in means.items()}
    rows = []
    for cell in means:
        others = [pooled[c] for c in means if c != cell]
        row = {"cell": cell, "recording": f"{cell} (all)", "mean_by_value": pooled[cell], "chosen": None, "scores": None}
        if others:
            score = {v: sum(o[v] for o in others) / len(others) for v in values}
            chosen = min(values, key=lambda v: (score[v], values.index(v)))
            row.update(chosen=chosen, scores=dict(means[cell][chosen]))
        rows.append(row)
    return rows


def paired_difference(values: list[str], conditions: list[str], grid: dict, reference: str) -> dict[str, dict]:
    """Each value's pooled score minus ``reference``'s, with its standard error, paired by recording.

    Pooled as :func:`leave_one_cell_out` pools: per cell the mean over its recordings (each
    recording's mean over the conditions), then the mean over cells.  The standard error is that
    of the cell means of the per-recording differences (``sd / sqrt(n)``), combined over cells
    as independent.  ``{value: {"diff": Δ, "se": SE, "moves": Δ < -MOVE_MARGIN_SE·SE}}``."""
    if reference not in values:
        raise GridError(f"reference value '{reference}' is not in the grid ({', '.join(values)})")
    out: dict[str, dict] = {}
    for v in values:
        if v == reference:
            continue
        diffs, variances = [], []
        for recs in grid.values():
            cell_diff, cell_se = paired_difference_of([(sum(bv[v].values()) / len(conditions),
                                                        sum(bv[reference].values()) / len(conditions))
                                                       for bv in recs.values()])
            diffs.append(cell_diff)
            variances.append(cell_se * cell_se)
        diff = statistics.fmean(diffs)
        se = math.sqrt(sum(variances)) / len(diffs)
        out[v] = {"diff": diff, "se": se, "moves": diff < -MOVE_MARGIN_SE * se}
    return out


def paired_row(paired: dict[str, dict], values: list[str], reference: str, n_before: int) -> str:
    """The table row of :func:`paired_difference` under the ``mean at`` columns (``n_before``
    empty cells first): Δ ± SE per value, the reference marked, a value that clears the margin bold."""
    cells = []
    for v in values:
        if v == reference:
            cells.append("(reference)")
            continue
        p = paired[v]
        text = f"{p['diff']:+.3f} ± {p['se']:.3f}"
        cells.append(f"**{text}**" if p["moves"] else text)
    return (f"| **Δ vs {reference} ± SE** |" + " |" * n_before + " " + " | ".join(cells) + " |")


def markdown(values: list[str], conditions: list[str], tuned: dict[str, list[dict]],
             paired: dict[str, dict] | None = None, reference: str | None = None) -> str:
    """One table: per estimator the value chosen for each recording and its scores at it; with a
    single estimator also every recording's mean score at each value of the grid."""
    one = len(tuned) == 1
    head = "| recording | " + " | ".join(
        f"{e} chosen | " + " | ".join(f"{e} {c}" for c in conditions) for e in tuned)
    head += (" | " + " | ".join(f"mean at {v}" for v in values) if one else "") + " |"
    width = 1 + len(tuned) * (1 + len(conditions)) + (len(values) if one else 0)
    out = [head, "|" + "---|" * width]
    per_est = list(tuned.values())
    for i, first in enumerate(per_est[0]):
        cells = []
        for rows in per_est:
            r = rows[i]
            got = " | ".join("-" if r["scores"] is None else f"**{r['scores'][c]:.2f}**" for c in conditions)
            cells.append(f"{r['chosen'] or '-'} | {got}")
        at = (" | " + " | ".join(f"{first['mean_by_value'][v]:.2f}" for v in values)) if one else ""
        out.append(f"| {first['recording']} | " + " | ".join(cells) + at + " |")
    cells = []
    for rows in per_est:
        scored = [r for r in rows if r["scores"] is not None]
        got = " | ".join(f"**{sum(r['scores'][c] for r in scored) / max(len(scored), 1):.2f}**" for c in conditions)
        cells.append(f" | {got}")
    rows0 = per_est[0]
    at = (" | " + " | ".join(f"{sum(r['mean_by_value'][v] for r in rows0) / len(rows0):.2f}" for v in values)) if one else ""
    out.append("| **mean** | " + " | ".join(cells) + at + " |")
    if one and paired and reference:
        out.append(paired_row(paired, values, reference, 1 + len(conditions)))
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m research.nested_tuning",
        description="Leave-one-out choice of a tuning value: each recording is scored with the value that "
                    "did best on the other recordings of its cell (never on itself).",
    )
    p.add_argument("pairs", nargs="+", metavar="VALUE=RESULTS.json[@CELL]",
                   help="a 'socd evaluate --json' file run with the setting at VALUE (repeat per file); @CELL "
                        "names its cell when it is not the profile in the file")
    p.add_argument("--estimator", action="append", required=True,
                   help="estimator whose rows are tuned, e.g. fomiukf (repeat to tune several side by side, "
                        "each on its own)")
    p.add_argument("--metric", default=METRIC, help=f"score to minimise (default {METRIC})")
    p.add_argument("--by", choices=("recording", "cell"), default="recording",
                   help="leave one recording out within its cell (default), or one whole cell out: the value "
                        "chosen on the other cells is scored on the held-out cell (how defaults are chosen)")
    p.add_argument("--reference", metavar="VALUE",
                   help="the current default: add each value's pooled score minus it, with the standard error "
                        f"of that paired difference; a value moves the default only when it is lower by more "
                        f"than {MOVE_MARGIN_SE:g} standard errors (bold). One estimator only")
    p.add_argument("--exclude", metavar="REGEX",
                   help="leave out the recordings whose name matches (e.g. '_10C_trise': DESIGN §7 scores the "
                        "Panasonic 10 °C trise files in their own row and tunes nothing for them)")
    p.add_argument("--json", metavar="OUT", help="write the rows as JSON")
    args = p.parse_args(argv)
    if args.exclude:
        try:
            re.compile(args.exclude)
        except re.error as exc:
            p.error(f"--exclude {args.exclude!r}: not a regular expression ({exc})")
    if args.reference and len(args.estimator) > 1:
        p.error("--reference compares the values of one estimator; give one --estimator")
    tuned: dict[str, list[dict]] = {}
    paired: dict[str, dict] | None = None
    try:
        for est in args.estimator:
            values, conditions, grid = load_grid(args.pairs, est, args.metric, args.exclude)
            choose = leave_one_cell_out if args.by == "cell" else leave_one_out
            tuned[est] = choose(values, conditions, grid)
            if args.reference:
                paired = paired_difference(values, conditions, grid, args.reference)
    except GridError as exc:
        print(f"nested_tuning: error: {exc}", file=sys.stderr)
        return 2
    recs = [[r["recording"] for r in rows] for rows in tuned.values()]
    if any(r != recs[0] for r in recs):
        print("nested_tuning: error: the estimators were not run on the same recordings", file=sys.stderr)
        return 2
    print(markdown(values, conditions, tuned, paired, args.reference))
    if args.json:
        doc = {"metric": args.metric, "values": values, "conditions": conditions, "estimators": tuned,
               "excluded": args.exclude}
        if paired is not None:
            doc.update(reference=args.reference, paired=paired, move_margin_se=MOVE_MARGIN_SE)
        Path(args.json).write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
