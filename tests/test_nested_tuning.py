"""Leave-one-out choice of a tuning value (research.nested_tuning) on real JSON files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from research.nested_tuning import (
    GridError,
    leave_one_cell_out,
    leave_one_out,
    load_grid,
    main,
    paired_difference,
)

pytestmark = pytest.mark.research


def _results(path: Path, cell: str, scores: dict[str, float], estimator: str = "ecm2rc-ekf",
             bias: float = 0.0) -> str:
    path.write_text(json.dumps({"cell": cell, "current_bias_c": bias, "results": [
        {"recording": r, "estimator": estimator, "soc_rmse_after_600s_pct": s} for r, s in scores.items()]}))
    return str(path)


def test_each_file_gets_the_value_best_on_the_others(tmp_path: Path) -> None:
    # value "lo" is best on a and b, "hi" on c; c alone prefers hi, but c never votes for itself
    lo = _results(tmp_path / "lo.json", "cellA", {"a": 0.2, "b": 0.3, "c": 0.9})
    hi = _results(tmp_path / "hi.json", "cellA", {"a": 0.4, "b": 0.5, "c": 0.1})
    single = _results(tmp_path / "x.json", "cellB", {"z": 0.5})
    single_hi = _results(tmp_path / "xh.json", "cellB", {"z": 0.4})
    values, conds, grid = load_grid([f"lo={lo}", f"hi={hi}", f"lo={single}", f"hi={single_hi}"], "ecm2rc-ekf")
    rows = {r["recording"]: r for r in leave_one_out(values, conds, grid)}
    assert values == ["lo", "hi"] and conds == ["bias +0C"]
    # a: others b (lo 0.3, hi 0.5) and c (0.9, 0.1): means 0.6 vs 0.3 -> hi
    assert rows["a"]["chosen"] == "hi" and rows["a"]["scores"]["bias +0C"] == pytest.approx(0.4)
    assert rows["b"]["chosen"] == "hi" and rows["b"]["scores"]["bias +0C"] == pytest.approx(0.5)
    # c: others a, b prefer lo, so c is scored at lo (0.9) although hi would give 0.1
    assert rows["c"]["chosen"] == "lo" and rows["c"]["scores"]["bias +0C"] == pytest.approx(0.9)
    assert rows["z"]["chosen"] is None and rows["z"]["scores"] is None  # nothing to choose on


def test_a_value_that_only_wins_without_an_offset_is_not_chosen(tmp_path: Path) -> None:
    """Pooled over conditions: "hi" wins without a sensor offset and loses more with one."""
    f = {}
    for v, clean, biased in (("lo", {"a": 0.3, "b": 0.3, "c": 0.3}, {"a": 0.5, "b": 0.5, "c": 0.5}),
                             ("hi", {"a": 0.1, "b": 0.1, "c": 0.1}, {"a": 1.0, "b": 1.0, "c": 1.0})):
        f[v] = [_results(tmp_path / f"{v}0.json", "c", clean), _results(tmp_path / f"{v}1.json", "c", biased, bias=0.01)]
    values, conds, grid = load_grid([f"{v}={p}" for v in f for p in f[v]], "ecm2rc-ekf")
    assert conds == ["bias +0C", "bias +0.01C"]
    rows = leave_one_out(values, conds, grid)
    assert {r["chosen"] for r in rows} == {"lo"}
    assert rows[0]["scores"] == {"bias +0C": pytest.approx(0.3), "bias +0.01C": pytest.approx(0.5)}
    # only the clean runs: hi is chosen
    values, conds, grid = load_grid([f"{v}={f[v][0]}" for v in f], "ecm2rc-ekf")
    assert {r["chosen"] for r in leave_one_out(values, conds, grid)} == {"hi"}


def test_bad_grids_name_the_problem(tmp_path: Path, capsys) -> None:
    a = _results(tmp_path / "a.json", "c", {"r1": 0.1, "r2": 0.2})
    b = _results(tmp_path / "b.json", "c", {"r1": 0.1})
    with pytest.raises(GridError, match="r2 has no result for value 2 under bias"):
        load_grid([f"1={a}", f"2={b}"], "ecm2rc-ekf")
    with pytest.raises(GridError, match="no results for estimator 'fomiukf'"):
        load_grid([f"1={a}"], "fomiukf")
    with pytest.raises(GridError, match="expected VALUE=RESULTS.json"):
        load_grid([a], "ecm2rc-ekf")
    assert main(["--estimator", "ecm2rc-ekf", f"1={tmp_path / 'missing.json'}"]) == 2
    assert "missing.json" in capsys.readouterr().err


def test_cli_prints_table_and_writes_json(tmp_path: Path, capsys) -> None:
    lo = _results(tmp_path / "lo.json", "c", {"a": 0.2, "b": 0.3})
    hi = _results(tmp_path / "hi.json", "c", {"a": 0.4, "b": 0.1})
    assert main(["--estimator", "ecm2rc-ekf", f"lo={lo}", f"hi={hi}", "--json", str(tmp_path / "o.json")]) == 0
    out = capsys.readouterr().out
    assert "| a | hi | **0.40** |" in out and "| b | lo | **0.30** |" in out and "ecm2rc-ekf bias +0C" in out
    doc = json.loads((tmp_path / "o.json").read_text())
    assert doc["values"] == ["lo", "hi"] and len(doc["estimators"]["ecm2rc-ekf"]) == 2


def test_two_estimators_side_by_side_each_tuned_on_its_own(tmp_path: Path, capsys) -> None:
    pairs = []
    for v, ekf, ours in (("lo", {"a": 0.2, "b": 0.3}, {"a": 0.5, "b": 0.6}), ("hi", {"a": 0.4, "b": 0.1}, {"a": 0.1, "b": 0.2})):
        path = tmp_path / f"{v}.json"
        path.write_text(json.dumps({"cell": "c", "results": [
            *({"recording": r, "estimator": "ecm2rc-ekf", "soc_rmse_after_600s_pct": x} for r, x in ekf.items()),
            *({"recording": r, "estimator": "fomiukf", "soc_rmse_after_600s_pct": x} for r, x in ours.items())]}))
        pairs.append(f"{v}={path}")
    assert main(["--estimator", "fomiukf", "--estimator", "ecm2rc-ekf", *pairs]) == 0
    out = capsys.readouterr().out
    # fomiukf: hi is best on either other file; the EKF: a chooses on b (hi), b on a (lo)
    assert "| a | hi | **0.10** | hi | **0.40** |" in out
    assert "| b | hi | **0.20** | lo | **0.30** |" in out
    assert "mean at" not in out


def test_leave_one_cell_out_scores_each_cell_with_the_value_the_others_chose(tmp_path: Path) -> None:
    """Cells weigh the same however many recordings they have; a cell never votes for itself."""
    pairs = []
    for v, scores in (("lo", {"A": {"a1": 0.2, "a2": 0.2, "a3": 0.2}, "B": {"b": 0.3}, "C": {"c": 0.9}}),
                      ("hi", {"A": {"a1": 0.3, "a2": 0.3, "a3": 0.3}, "B": {"b": 0.6}, "C": {"c": 0.1}})):
        for cell, s in scores.items():
            pairs.append(f"{v}={_results(tmp_path / f'{v}{cell}.json', cell, s)}")
    values, conds, grid = load_grid(pairs, "ecm2rc-ekf")
    rows = {r["cell"]: r for r in leave_one_cell_out(values, conds, grid)}
    # A held out: B (lo 0.3, hi 0.6) and C (0.9, 0.1) -> lo 0.6, hi 0.35 -> hi, scored 0.3
    assert rows["A"]["chosen"] == "hi" and rows["A"]["scores"]["bias +0C"] == pytest.approx(0.3)
    # C held out: A (0.2, 0.3), B (0.3, 0.6) -> lo; C scores 0.9 although hi gives 0.1 on it
    assert rows["C"]["chosen"] == "lo" and rows["C"]["scores"]["bias +0C"] == pytest.approx(0.9)
    assert rows["B"]["chosen"] == "hi" and rows["B"]["scores"]["bias +0C"] == pytest.approx(0.6)
    assert main(["--by", "cell", "--estimator", "ecm2rc-ekf", *pairs]) == 0


def test_at_cell_joins_two_profiles_of_one_cell(tmp_path: Path) -> None:
    a = _results(tmp_path / "a.json", "profile_hppc.toml", {"r1": 0.5})
    b = _results(tmp_path / "b.json", "profile_us06.toml", {"r1": 0.7})  # the same file, another profile
    values, conds, grid = load_grid([f"v={a}@pan", f"v={b}@pan"], "ecm2rc-ekf")
    assert list(grid) == ["pan"] and set(grid["pan"]) == {"pan#1/r1", "pan#2/r1"}
    assert grid["pan"]["pan#1/r1"]["v"]["bias +0C"] == pytest.approx(0.5)
    # each value with its own profiles (another `socd fit` option): matched by their place
    c = _results(tmp_path / "c.json", "profile_hppc_kin.toml", {"r1": 0.4})
    d = _results(tmp_path / "d.json", "profile_us06_kin.toml", {"r1": 0.9})
    _, _, grid = load_grid([f"v={a}@pan", f"v={b}@pan", f"w={c}@pan", f"w={d}@pan"], "ecm2rc-ekf")
    assert grid["pan"]["pan#1/r1"]["w"]["bias +0C"] == pytest.approx(0.4)
    assert grid["pan"]["pan#2/r1"]["w"]["bias +0C"] == pytest.approx(0.9)
    with pytest.raises(GridError):
        load_grid(["v="], "ecm2rc-ekf")


def test_paired_difference_separates_a_consistent_gain_from_a_noisy_one(tmp_path: Path) -> None:
    """A value better on every recording by 0.1 clears the margin; one with the same mean gain made of
    large swings either way is a tie, and the default stays."""
    ref = {"a": 1.0, "b": 1.0, "c": 1.0, "d": 1.0}
    steady = {k: v - 0.1 for k, v in ref.items()}
    noisy = {"a": 0.2, "b": 1.8, "c": 0.4, "d": 1.2}  # mean 0.9, the same pooled gain
    paths = {name: _results(tmp_path / f"{name}.json", "cellA", s)
             for name, s in (("ref", ref), ("steady", steady), ("noisy", noisy))}
    values, conds, grid = load_grid([f"{n}={p}" for n, p in paths.items()], "ecm2rc-ekf")
    paired = paired_difference(values, conds, grid, "ref")
    assert paired["steady"]["diff"] == pytest.approx(-0.1) and paired["steady"]["se"] == pytest.approx(0.0, abs=1e-12)
    assert paired["steady"]["moves"]
    assert paired["noisy"]["diff"] == pytest.approx(-0.1) and paired["noisy"]["se"] > 0.1
    assert not paired["noisy"]["moves"]
    with pytest.raises(GridError, match="reference value 'x' is not in the grid"):
        paired_difference(values, conds, grid, "x")


def test_reference_row_in_the_table_and_json(tmp_path: Path, capsys) -> None:
    lo = _results(tmp_path / "lo.json", "c1", {"a": 0.5, "b": 0.6})
    hi = _results(tmp_path / "hi.json", "c1", {"a": 0.4, "b": 0.5})
    lo2 = _results(tmp_path / "lo2.json", "c2", {"z": 0.5, "y": 0.7})
    hi2 = _results(tmp_path / "hi2.json", "c2", {"z": 0.4, "y": 0.6})
    out = tmp_path / "t.json"
    assert main(["--by", "cell", "--estimator", "ecm2rc-ekf", "--reference", "lo", f"lo={lo}", f"hi={hi}",
                 f"lo={lo2}", f"hi={hi2}", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| **Δ vs lo ± SE** |" in text and "(reference)" in text and "**-0.100 ± 0.000**" in text
    doc = json.loads(out.read_text())
    assert doc["reference"] == "lo" and doc["paired"]["hi"]["moves"] is True
    assert main(["--estimator", "ecm2rc-ekf", "--reference", "nope", f"lo={lo}", f"hi={hi}"]) == 2
    assert "reference value 'nope'" in capsys.readouterr().err


def test_excluded_recordings_take_no_part_in_the_choice(tmp_path: Path, capsys) -> None:
    """``--exclude``: a recording scored elsewhere (the Panasonic 10 °C trise files, DESIGN §7)
    neither votes nor is scored; a pattern that is not a regular expression is refused."""
    lo = _results(tmp_path / "lo.json", "cellA", {"a": 0.3, "b": 0.3, "x_10C_trise_1": 5.0})
    hi = _results(tmp_path / "hi.json", "cellA", {"a": 0.4, "b": 0.4, "x_10C_trise_1": 0.1})
    values, conds, grid = load_grid([f"lo={lo}", f"hi={hi}"], "ecm2rc-ekf")
    chosen = {r["recording"]: r["chosen"] for r in leave_one_out(values, conds, grid)}
    assert chosen["a"] == chosen["b"] == "hi"  # the trise file outvotes the others
    values, conds, grid = load_grid([f"lo={lo}", f"hi={hi}"], "ecm2rc-ekf", exclude="_10C_trise")
    rows = leave_one_out(values, conds, grid)
    assert [r["recording"] for r in rows] == ["a", "b"] and {r["chosen"] for r in rows} == {"lo"}
    out = tmp_path / "t.json"
    assert main(["--estimator", "ecm2rc-ekf", "--exclude", "_10C_trise", f"lo={lo}", f"hi={hi}",
                 "--json", str(out)]) == 0
    assert json.loads(out.read_text())["excluded"] == "_10C_trise"
    assert "x_10C_trise_1" not in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--estimator", "ecm2rc-ekf", "--exclude", "(", f"lo={lo}"])
    assert "not a regular expression" in capsys.readouterr().err
