"""A development set for ``socd diagnose``, and its rules chosen leave-one-cell-out.

The labelled synthetic files are one cell on a handful of drives; rules tuned on them lose power
on other cells.  This module builds a larger set the same way (PyBaMM SPMe with a lumped thermal
model, the effects of :mod:`research.validate_pybamm` at three levels, the labelled files' noise)
over several parameter sets and drive kinds, diagnoses every recording once with the product's
pipeline, and chooses the significance rules on all cells but one, scoring them on that one.

Three stages, each cached in ``--workdir`` (a file already there is not made again)::

    python -m research.devset build     [--workdir out/devset] [--jobs 2]
    python -m research.devset evidence  [--workdir out/devset] [--jobs 2]
    python -m research.devset labelled  [--labelled ../shared/data/synthetic] [--jobs 2]
    python -m research.devset rules     [--workdir out/devset] [--json OUT] [--markdown OUT]

The labelled stage diagnoses the shared labelled files the same way; the rules stage puts them
with their own cell's recordings (``labels.json`` names it), so they are held out with that cell.

* ``build`` simulates every recording of :func:`plan` (``STEM.csv``, ``STEM_ocv.csv``, the
  fresh cell's OCV table the user would have, and ``STEM.json``, the truth).
* ``evidence`` diagnoses each recording as ``socd diagnose STEM.csv --ocv STEM_ocv.csv
  --capacity-ah X`` does, on the chronological split, and scores every effect its signature
  nominated on the confirmation split as well (whatever the verdict), so the verdict under any
  significance rule can be worked out again from the figures (``STEM.evidence.json``).
* ``rules`` re-decides every verdict over :data:`RULE_GRID` with the pipeline's own
  :func:`~service.diagnosis.pipeline.significance_reasons` and
  :func:`~service.diagnosis.pipeline.rank`; for each cell the rule with the fewest verdicts
  wrong on the *other* cells, a false alarm on a clean recording counted as
  :data:`FALSE_ALARM_COST` wrong verdicts, is scored on the held-out cell.  Reported per cell and pooled: the confusion matrix, false alarms on clean
  recordings, detection by level, the held-out RMSE cut of the named effect and the share of
  the effect's part of the held-out RMSE it removed, against the recording's clean twin (the
  clean recording of the same cell and drive, whose base held-out RMSE is the model's floor).

Each cell gets every effect at three levels, each on one of the drive kinds (rotating, so every
effect meets every drive over the cells), and one clean recording per drive kind; all the
recordings of a cell and drive kind share one current profile, so the clean one is the others'
twin.  Needs PyBaMM (``pip install -e .[research]``).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import itertools
import json
import math
import statistics
import sys
from collections import Counter
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from research.validate_pybamm import EFFECTS, LEVELS

#: PyBaMM parameter sets: the labelled files' cell (OKane2022), four other NMC/NCA cells, an
#: LFP cell (Prada2013), and two small cells whose current sensor's noise crosses the rest level
#: (NCA_Kim2011, 0.48 Ah; Ecker2015, 0.17 Ah).  Appended, so the first six keep their seeds.
CELLS = ("OKane2022", "Chen2020", "Mohtat2020", "Marquis2019", "Ai2020", "Prada2013", "NCA_Kim2011", "Ecker2015")
#: drive kinds (research.validate_pybamm.drive): a drive cycle without long rests, one with parking
#: rests, HPPC, a random walk with charging
DRIVES = ("dst", "rests", "hppc", "walk")
DEFAULT_WORKDIR = Path("out/devset")
#: the shared labelled recordings: in the rule search with their cell's recordings (held out with it)
LABELLED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "synthetic"
#: the level of a clean recording on a drive profile of its own (not a twin), for the false-alarm count
REPEAT = "repeat"
#: drive kinds with a second clean recording per cell (their own seed)
REPEAT_DRIVES = ("dst", "hppc", "walk")


@dataclass(frozen=True)
class Spec:
    """One development recording: the cell, its effect and level, the drive and its seed."""

    cell: str
    effect: str
    level: str
    drive: str
    seed: int

    @property
    def stem(self) -> str:
        level = "clean" if self.effect == "none" and self.level != REPEAT else self.level
        return f"{self.cell}_{self.effect}_{level}_{self.drive}"

    @property
    def twin_stem(self) -> str:
        return f"{self.cell}_none_clean_{self.drive}"


def plan(cells: Sequence[str] = CELLS) -> list[Spec]:
    """Every recording of the set: per cell, each effect at each level on a drive that rotates with
    the effect, the level and the cell, plus one clean recording per drive kind and a second one,
    on a profile of its own, for each of :data:`REPEAT_DRIVES`.  The seed depends
    on the cell and the drive only (one current profile per cell and drive: the clean twin)."""
    specs = []
    for c, cell in enumerate(cells):
        seed_of = {d: 1000 * (c + 1) + 10 * k + 1 for k, d in enumerate(DRIVES)}
        for d in DRIVES:
            specs.append(Spec(cell, "none", LEVELS[1], d, seed_of[d]))
        for d in REPEAT_DRIVES:
            specs.append(Spec(cell, "none", REPEAT, d, seed_of[d] + 5))
        for e, effect in enumerate(x for x in EFFECTS if x != "none"):
            for k, level in enumerate(LEVELS):
                d = DRIVES[(e + k + c) % len(DRIVES)]
                specs.append(Spec(cell, effect, level, d, seed_of[d]))
    return specs


# -- build -----------------------------------------------------------------------------------------
def build_one(job: tuple[Spec, str]) -> tuple[str, str]:
    """Simulate one recording into ``workdir`` unless it is there; ``(stem, status)``."""
    from research.validate_pybamm import _pybamm, simulate
    from service.recording import save_recording

    spec, workdir = job
    out = Path(workdir)
    if (out / f"{spec.stem}.json").exists():
        return spec.stem, "cached"
    try:
        level = spec.level if spec.level in LEVELS else LEVELS[1]  # a clean repeat has no level
        data, soc, ocv, info = simulate(spec.cell, spec.effect, level, spec.seed, spec.drive)
    except (RuntimeError, _pybamm().SolverError) as exc:
        (out / f"{spec.stem}.failed").write_text(f"{type(exc).__name__}: {exc}\n")
        return spec.stem, f"not simulated: {type(exc).__name__}: {exc}"
    save_recording(out / f"{spec.stem}.csv", data)
    np.savetxt(out / f"{spec.stem}_ocv.csv", np.column_stack([soc, ocv]), delimiter=",", header="soc,ocv_v",
               comments="", fmt="%.5f")
    info.update(stem=spec.stem, twin=spec.twin_stem, samples=len(data))
    (out / f"{spec.stem}.json").write_text(json.dumps(info, indent=1))
    return spec.stem, "simulated"


# -- evidence --------------------------------------------------------------------------------------
@dataclass
class Candidate:
    """One effect's figures on one split, as :func:`~service.diagnosis.pipeline.rank` reads them,
    with the reasons that do not depend on the significance rules (a fitted size of a healthy
    cell, a missing signature)."""

    name: str
    score: float
    rmse_before_mv: float
    rmse_after_mv: float
    delta_bic: float
    evidence: str
    fixed_reasons: list[str] = field(default_factory=list)
    significant: bool = False
    #: the fitted size a plausibility bound reads (kinetics: the exchange current in C; diffusion:
    #: the surface lag's time constant in s; capacity: the capacity scale), if any
    size: float | None = None
    #: a directly measured effect retried on the confirmation split (significance_reasons' ``measured``)
    measured: bool = False
    #: the standard error of ln ``size`` from the fit (diffusion: σ(ln τ)), if any
    size_ln_std: float | None = None


@dataclass
class Evidence:
    """What the rules need of one recording's diagnosis (``STEM.evidence.json``)."""

    stem: str
    cell: str
    effect: str
    level: str
    drive: str
    noise_mv: float
    base_rmse_heldout_mv: float
    candidates: list[Candidate]
    confirm_noise_mv: float | None
    confirm_candidates: list[Candidate]
    #: seconds of the diagnosis the default rules run (the confirmation only where they retry)
    seconds_chronological: float
    seconds_confirmation: float
    #: the model-free signatures' statistics the signature rules read (:func:`signature_stats`)
    signatures: dict[str, dict] = field(default_factory=dict)

    @classmethod
    def from_json(cls, doc: dict) -> Evidence:
        doc = dict(doc)
        doc["candidates"] = [_candidate_from_json(c) for c in doc["candidates"]]
        doc["confirm_candidates"] = [_candidate_from_json(c) for c in doc["confirm_candidates"]]
        return cls(**doc)


#: how the kinetics extension's plausibility reason begins (service.diagnosis.effects._kin_implausible)
KINETICS_SIZE_REASON = "fitted exchange current "


def _candidate_from_json(doc: dict) -> Candidate:
    """A cached candidate; one cached before ``size`` was stored gets the kinetics exchange
    current back from its plausibility reason, which prints it (two decimals)."""
    c = Candidate(**doc)
    if c.size is None and c.name == "kinetics":
        for r in c.fixed_reasons:
            if r.startswith(KINETICS_SIZE_REASON):
                c.size = float(r[len(KINETICS_SIZE_REASON):].split()[0])
    return c


def signature_stats(sig: dict) -> dict[str, dict]:
    """What the signature rules of :data:`SIGNATURE_RULES` read from a diagnosis's signatures
    (``Diagnosis.signatures``): the kinetics step fit's exchange current and its 95 % upper bound,
    the diffusion relaxation ratio and its z, the capacity check's scale and interval, and the
    hysteresis signatures' statistics (the rest ends' half-gap fit and the direction state in the
    base residual)."""
    kin, rel, temp = sig.get("kinetics", {}), sig.get("diffusion", {}), sig.get("temperature", {})
    out = {"kinetics": {"i0_upper_c": kin.get("i0_upper_c"), "resolved": bool(kin.get("resolved", False))},
           "diffusion": {"statistic": rel.get("statistic") if "z" in rel else None, "z": rel.get("z")},
           "temperature": {"opening_c": temp.get("opening_temp_c"), "coldest_c": temp.get("coldest_temp_c"),
                           "nominal_c": temp.get("nominal_ambient_c")}}
    cap = sig.get("capacity")
    if cap is not None:  # the two-point check (service.diagnosis.signatures.two_point_capacity)
        out["capacity"] = {"nominated": bool(cap.get("nominated")), "skipped": cap.get("skipped"),
                           "scale": cap.get("capacity_scale"), "range": cap.get("capacity_scale_range"),
                           "drawn_soc": cap.get("drawn_soc")}
    if "hysteresis" in sig:  # read with the base model's residual: a diagnosis has it, the recording alone not
        branch = sig["hysteresis"]
        direction = branch.get("direction", {})
        out["hysteresis"] = ({k: branch.get(k) for k in ("n_rests", "statistic", "half_gap_v", "spread", "relaxation")}
                             | {"direction_z": direction.get("statistic"),
                                "direction_half_gap_v": direction.get("half_gap_v")})
    return out


def rest_key(min_rest_s: float) -> str:
    """The key of one rest length in ``signatures["diffusion_by_rest"]`` (JSON keys are strings)."""
    return f"{min_rest_s:g}"


def relaxation_by_rest(rec, capacity_ah: float, opt) -> dict[str, dict]:
    """The diffusion relaxation signature's statistic and z (as :func:`signature_stats` keeps them)
    on the fit part of ``opt.split``, read from rests of each length of :data:`RELAX_REST_GRID`."""
    from service.diagnosis.pipeline import held_out_mask
    from service.diagnosis.signatures import rest_relaxation

    fit = ~held_out_mask(rec.time_s, opt)
    out = {}
    for length in RELAX_REST_GRID:
        sig = rest_relaxation(rec.time_s, rec.current_a, rec.voltage_v, capacity_ah, usable=fit, min_rest_s=length)
        out[rest_key(length)] = signature_stats({"diffusion": sig})["diffusion"]
    return out


def confirm_unread(sub_signatures: dict) -> list[str]:
    """The effects whose fit-part signature found nothing to read on the confirmation split."""
    from service.diagnosis.pipeline import FIT_PART_SIGNATURES, signature_unread

    return [n for n in FIT_PART_SIGNATURES if signature_unread(sub_signatures, n)]


def recording_signature_stats(rec, capacity_ah: float, opt) -> dict:
    """:func:`signature_stats` and :func:`confirm_unread` computed from the recording itself, on the
    fit parts of ``opt.split`` and ``opt.confirm_split``, as the pipeline computes them (for
    evidence cached before they were kept)."""
    from service.diagnosis.pipeline import fit_part_signatures, held_out_mask
    from service.diagnosis.signatures import temperature_signature

    first = fit_part_signatures(rec, capacity_ah, ~held_out_mask(rec.time_s, opt))
    first["temperature"] = temperature_signature(rec.time_s, rec.current_a, rec.temperature_c, capacity_ah,
                                                 opt.nominal_ambient_c)
    retry = fit_part_signatures(rec, capacity_ah, ~held_out_mask(rec.time_s, replace(opt, split=opt.confirm_split)))
    return {**signature_stats(first), "confirm_unread": confirm_unread(retry),
            "diffusion_by_rest": relaxation_by_rest(rec, capacity_ah, opt)}


def _candidates(dg, opt) -> list[Candidate]:
    """The effects of a diagnosis as candidates, the rule-dependent reasons taken out."""
    from service.diagnosis.pipeline import significance_reasons

    noise_mv = dg.thresholds["noise_sigma_mv"]
    cap = dg.base_profile.effective_capacity_ah
    out = []
    for e in dg.effects:
        n_rule = len(significance_reasons(e.score, e.rmse_before_mv, e.rmse_after_mv, e.delta_bic, noise_mv,
                                          e.evidence, opt))
        size = (e.params["kinetics_i0_a"] / cap if e.name == "kinetics"
                else e.params["tau_s"] if e.name == "diffusion"
                else e.params["capacity_scale"] if e.name == "capacity" else None)
        # the kinetics and diffusion extensions' first coordinate is ln(size)
        ln_std = e.coordinates_std[0] if e.name in ("kinetics", "diffusion") and e.coordinates_std else None
        out.append(Candidate(name=e.name, score=float(e.score), rmse_before_mv=float(e.rmse_before_mv),
                             rmse_after_mv=float(e.rmse_after_mv), delta_bic=float(e.delta_bic), evidence=e.evidence,
                             fixed_reasons=list(e.reasons[n_rule:]), size=size, size_ln_std=ln_std))
    return out


def evidence_of(spec: Spec, dg, sub, opt) -> Evidence:
    """The rule-independent figures of ``dg`` (the chronological diagnosis) and ``sub`` (its
    nominated and directly measured effects on the confirmation split, or ``None``) under the options ``opt`` they ran with."""
    from service.diagnosis.pipeline import retry_candidates

    retried = dg.verdict == "none" and bool(retry_candidates(dg.effects))
    return Evidence(stem=spec.stem, cell=spec.cell, effect=spec.effect, level=spec.level, drive=spec.drive,
                    noise_mv=dg.thresholds["noise_sigma_mv"], base_rmse_heldout_mv=float(dg.base["rmse_heldout_mv"]),
                    candidates=_candidates(dg, opt),
                    confirm_noise_mv=sub.thresholds["noise_sigma_mv"] if sub is not None else None,
                    confirm_candidates=_candidates(sub, opt) if sub is not None else [],
                    seconds_chronological=dg.seconds,
                    # what the default rules spend: the retry runs only on a none verdict with a
                    # nominated effect short of its bar
                    seconds_confirmation=sub.seconds if sub is not None and retried else 0.0,
                    signatures={**signature_stats(dg.signatures),
                                "confirm_unread": confirm_unread(sub.signatures) if sub is not None else [],
                                "diffusion_by_rest": relaxation_by_rest(dg.recording, dg.base_profile.effective_capacity_ah,
                                                                        opt)})


def diagnose_for_evidence(spec: Spec, rec, profile, opt) -> Evidence:
    """Diagnose ``rec`` on ``opt.split``, then every effect its signature nominated or measured on
    ``opt.confirm_split`` whatever the verdict, so :func:`decide` can retry under any rule."""
    from service.diagnosis.pipeline import _diagnose_on_split, signature_backed

    quiet = lambda _msg: None
    dg = _diagnose_on_split(rec, profile, opt, quiet)
    signed = signature_backed(dg.effects)
    sub = None
    if signed and opt.confirm_split and opt.confirm_split != opt.split:
        sub = _diagnose_on_split(rec, profile, replace(opt, split=opt.confirm_split, effects=signed), quiet)
    return evidence_of(spec, dg, sub, opt)


def write_evidence(spec: Spec, src: Path, stem: str, capacity_ah: float, path: Path) -> Evidence:
    """Diagnose ``src/STEM.csv`` with its OCV table ``src/STEM_ocv.csv`` and the default options, as
    ``socd diagnose --ocv --capacity-ah`` does, and write its evidence (named ``stem``) to ``path``."""
    from service.diagnosis.pipeline import DiagnoseOptions, table_profile
    from service.recording import load_recording

    ocv = np.loadtxt(src / f"{stem}_ocv.csv", delimiter=",", skiprows=1)
    ev = diagnose_for_evidence(spec, load_recording(src / f"{stem}.csv"),
                               table_profile(stem, capacity_ah, ocv[:, 0], ocv[:, 1]), DiagnoseOptions())
    ev.stem = stem
    path.write_text(json.dumps(asdict(ev), indent=1))
    return ev


def evidence_one(job: tuple[Spec, str]) -> tuple[str, str]:
    """Diagnose one recording of the set and write ``STEM.evidence.json``; ``(stem, status)``."""
    spec, workdir = job
    out = Path(workdir)
    path = out / f"{spec.stem}.evidence.json"
    if path.exists():
        return spec.stem, "cached"
    if not (out / f"{spec.stem}.json").exists():
        return spec.stem, "not built"
    info = json.loads((out / f"{spec.stem}.json").read_text())
    ev = write_evidence(spec, out, spec.stem, info["capacity_ah"], path)
    verdict, _ = decide(ev, {})
    return spec.stem, f"{verdict} ({ev.seconds_chronological + ev.seconds_confirmation:.0f} s)"


def labelled_one(job: tuple[str, str, str]) -> tuple[str, str]:
    """Diagnose one labelled recording of ``data`` (``STEM.csv``, ``STEM_ocv.csv``,
    ``STEM.meta.json``, the truth in ``labels.json``) into ``workdir`` as :func:`evidence_one`
    does; the rules stage puts it with its cell's recordings.  ``(stem, status)``."""
    stem, data, workdir = job
    path = Path(workdir) / f"{stem}.evidence.json"
    if path.exists():
        return stem, "cached"
    src = Path(data)
    label = json.loads((src / "labels.json").read_text())[stem]
    cap = json.loads((src / f"{stem}.meta.json").read_text())["capacity_ah"]
    spec = Spec("labelled", label["effect"], label.get("level") or LEVELS[1], label.get("profile", "?"), 0)
    ev = write_evidence(spec, src, stem, cap, path)
    return stem, f"{decide(ev, {})[0]} (truth {label['effect']})"


# -- rules -----------------------------------------------------------------------------------------
#: the shortest rest the diffusion relaxation signature reads (s), searched with ``rules
#: --search-rest-length``: a long rest reads the slow tail alone, a shorter one reads drives that park
#: only briefly (a random walk's rests of a few minutes) but also more of a healthy cell's faster
#: relaxation.  The evidence keeps the signature's statistic at every length (:func:`relaxation_by_rest`)
RELAX_REST_GRID: tuple[float, ...] = (60.0, 120.0, 300.0, 500.0)
#: the rules searched: significance thresholds (fields of DiagnoseOptions) and signature levels
#: (:data:`SIGNATURE_RULES`); each list holds the product's current value
RULE_GRID: dict[str, tuple[float, ...]] = {
    "min_rel_gain": (0.15, 0.20, 0.25, 0.30, 0.40),
    "min_rel_gain_nominated": (0.03, 0.05, 0.10, 0.15),
    "min_abs_gain_noise": (0.25, 0.5, 1.0),
    "min_delta_bic": (-10.0, 0.0, 10.0),
    "kinetics_max_i0_c": (0.10, 0.12, 0.15, 0.18, 0.20),
    "relax_min_ratio": (0.15, 0.20, 0.30),
    "relax_min_z": (3.0, 5.0),
    "direct_max_rise_rel": (0.10, 0.15, 0.20, 0.30),
    "capacity_min_change": (0.0, 0.02, 0.03, 0.05),
}
#: ``rules --wide-grid``: the axes whose chosen value sits at an edge of :data:`RULE_GRID`, extended past it
#: (a check that the choice is not held by the grid's edge; docs/results/diagnose.md)
WIDE_GRID: dict[str, tuple[float, ...]] = {
    **RULE_GRID,
    "min_abs_gain_noise": (0.25, 0.5, 1.0, 1.5),
    "min_delta_bic": (-20.0, -10.0, 0.0, 10.0),
    "relax_min_ratio": (0.05, 0.075, 0.10, 0.15, 0.20, 0.30),
    "relax_min_z": (3.0, 5.0, 8.0),
}
#: signature levels: the kinetics bound (service.diagnosis.effects.KINETICS_MAX_I0_C: the step fit
#: nominates kinetics below it and the extension's fitted exchange current must lie below it) and
#: the relaxation signature's ratio and z (service.diagnosis.signatures.RELAX_MIN_RATIO, RELAX_MIN_Z), and
#: with ``rules --search-rest-length`` the shortest rest it reads (RELAX_REST_MIN_S)
SIGNATURE_RULES = ("kinetics_max_i0_c", "relax_min_ratio", "relax_min_z", "relax_direct_ratio", "relax_rest_min_s",
                   "diffusion_signature",
                   "branch_min_z", "branch_min_half_gap_v", "direction_min_z", "diffusion_min_tau_s",
                   "lag_max_ln_tau_std", "capacity_min_change")
#: a structural rule the search leaves alone unless asked (``rules --search-requirement``): whether a
#: fit-only diffusion is refused never (0), where its relaxation signature read rests and did not
#: fire (1, the product), or always (2): the index into service.diagnosis.effects.SIGNATURE_NEEDED
REQUIREMENT_GRID: dict[str, tuple[float, ...]] = {"diffusion_signature": (0.0, 1.0, 2.0)}
#: ``rules --search-rest-length``: the relaxation signature's shortest rest, searched with the rest
REST_LENGTH_GRID: dict[str, tuple[float, ...]] = {"relax_rest_min_s": RELAX_REST_GRID}
#: ``rules --search-lag-bound``: the shortest surface lag the diffusion extension may fit and still be
#: slow diffusion (service.diagnosis.effects.DIFFUSION_MIN_TAU_S), searched with the rest
LAG_BOUND_GRID: dict[str, tuple[float, ...]] = {"diffusion_min_tau_s": (30.0, 60.0, 120.0)}
#: ``rules --search-lag-std``: how well the fit part must determine the surface lag's time constant
#: (service.diagnosis.effects.DIFFUSION_MAX_LN_TAU_STD, σ of ln τ; inf: not at all), searched with the rest
LAG_STD_GRID: dict[str, tuple[float, ...]] = {"lag_max_ln_tau_std": (0.75, 1.0, 1.5, math.inf)}
#: ``rules --search-direct-diffusion``: the relaxation ratio from which it measures slow diffusion directly
#: (service.diagnosis.signatures.RELAX_DIRECT_RATIO; inf: never, the product's).  Searched with the rest
#: on eight cells it reads fewer verdicts right held out than the search without it (docs/results/diagnose.md)
DIRECT_DIFFUSION_GRID: dict[str, tuple[float, ...]] = {"relax_direct_ratio": (math.inf, 0.25, 0.35, 0.50)}
#: ``rules --search-hysteresis``: the hysteresis signatures' levels (service.diagnosis.signatures
#: BRANCH_MIN_Z, BRANCH_MIN_HALF_GAP_V, DIRECTION_MIN_Z), searched with the rest
HYSTERESIS_GRID: dict[str, tuple[float, ...]] = {
    "branch_min_z": (3.0, 5.0, 8.0),
    "branch_min_half_gap_v": (0.002, 0.003, 0.004, 0.006),
    "direction_min_z": (4.0, 5.0, 6.0, 8.0, 12.0),
}


def current_rule() -> dict[str, float]:
    """The product's current value of every rule of :data:`RULE_GRID`."""
    from service.diagnosis import signatures
    from service.diagnosis.effects import (
        CAPACITY_MIN_CHANGE,
        DIFFUSION_MAX_LN_TAU_STD,
        DIFFUSION_MIN_TAU_S,
        EFFECTS,
        KINETICS_MAX_I0_C,
        SIGNATURE_NEEDED,
    )
    from service.diagnosis.pipeline import DiagnoseOptions

    opt = DiagnoseOptions()
    now = {k: getattr(opt, k) for k in RULE_GRID if k not in SIGNATURE_RULES}
    now.update(kinetics_max_i0_c=KINETICS_MAX_I0_C, relax_min_ratio=signatures.RELAX_MIN_RATIO,
               relax_min_z=signatures.RELAX_MIN_Z, relax_direct_ratio=signatures.RELAX_DIRECT_RATIO,
               relax_rest_min_s=signatures.RELAX_REST_MIN_S,
               diffusion_signature=float(SIGNATURE_NEEDED.index(EFFECTS["diffusion"].needs_signature)),
               branch_min_z=signatures.BRANCH_MIN_Z, branch_min_half_gap_v=signatures.BRANCH_MIN_HALF_GAP_V,
               direction_min_z=signatures.DIRECTION_MIN_Z, diffusion_min_tau_s=DIFFUSION_MIN_TAU_S,
               lag_max_ln_tau_std=DIFFUSION_MAX_LN_TAU_STD, capacity_min_change=CAPACITY_MIN_CHANGE)
    return now


def rule_axes(with_requirement: bool = False, wide: bool = False, with_rest_length: bool = False,
              with_hysteresis: bool = False, with_lag_bound: bool = False,
              with_direct_diffusion: bool = False, with_lag_std: bool = False) -> dict[str, tuple[float, ...]]:
    """The values searched per rule: :data:`RULE_GRID` (:data:`WIDE_GRID` with ``wide``), and
    :data:`REQUIREMENT_GRID` with ``with_requirement``, :data:`REST_LENGTH_GRID` with ``with_rest_length``,
    :data:`HYSTERESIS_GRID` with ``with_hysteresis``, :data:`LAG_BOUND_GRID` with ``with_lag_bound``,
    :data:`DIRECT_DIFFUSION_GRID` with ``with_direct_diffusion``, :data:`LAG_STD_GRID` with ``with_lag_std``."""
    return {**(WIDE_GRID if wide else RULE_GRID), **(REQUIREMENT_GRID if with_requirement else {}),
            **(REST_LENGTH_GRID if with_rest_length else {}), **(HYSTERESIS_GRID if with_hysteresis else {}),
            **(LAG_BOUND_GRID if with_lag_bound else {}), **(DIRECT_DIFFUSION_GRID if with_direct_diffusion else {}),
            **(LAG_STD_GRID if with_lag_std else {})}


def product_rule_grid(grid: Sequence[dict[str, float]]) -> list[dict[str, float]]:
    """``rules --product-rule``: the one rule the product ships, on the axes of ``grid``."""
    now = current_rule()
    return [{k: now[k] for k in grid[0]}]


def rule_grid(with_requirement: bool = False, wide: bool = False, with_rest_length: bool = False,
              with_hysteresis: bool = False, with_lag_bound: bool = False,
              with_direct_diffusion: bool = False, with_lag_std: bool = False) -> list[dict[str, float]]:
    """Every rule of :func:`rule_axes` with the same switches."""
    axes = rule_axes(with_requirement, wide, with_rest_length, with_hysteresis, with_lag_bound, with_direct_diffusion,
                     with_lag_std)
    keys = list(axes)
    return [dict(zip(keys, values)) for values in itertools.product(*(axes[k] for k in keys))]


def _with_signature_rules(cands: Iterable[Candidate], ev: Evidence, rule: dict[str, float],
                          confirmation: bool = False) -> list[Candidate]:
    """``cands`` with the evidence class and plausibility the signature levels in ``rule`` give
    (a level not in ``rule`` keeps the class the diagnosis ran with).  ``confirmation``: the
    candidates of the confirmation split, whose hysteresis class its own signatures decided (the
    evidence keeps only the first split's, so that class stays as the diagnosis left it)."""
    out = []
    for c in cands:
        if c.name == "diffusion" and "diffusion_min_tau_s" in rule and c.size is not None:
            c = _changed(c, fixed_reasons=_tau_reasons(c, rule["diffusion_min_tau_s"]))
        if c.name == "diffusion" and "lag_max_ln_tau_std" in rule:
            c = _changed(c, fixed_reasons=_undetermined_reasons(c, rule["lag_max_ln_tau_std"]))
        if c.name == "capacity" and c.size is not None:
            c = _changed(c, fixed_reasons=_capacity_reasons(c, rule.get("capacity_min_change")))
        if c.name == "kinetics" and "kinetics_max_i0_c" in rule:
            k = rule["kinetics_max_i0_c"]
            sig = ev.signatures["kinetics"]
            nominated = sig["i0_upper_c"] is not None and sig["i0_upper_c"] < k and sig["resolved"]
            fixed = [r for r in c.fixed_reasons if not r.startswith(KINETICS_SIZE_REASON)]
            if c.size is not None and c.size >= k:
                fixed.append(f"{KINETICS_SIZE_REASON}{c.size:.2f} C >= {k:g} C")
            c = _changed(c, evidence="nominated" if nominated else "fit", fixed_reasons=fixed)
        elif c.name == "diffusion" and {"relax_min_ratio", "relax_min_z", "relax_direct_ratio", "relax_rest_min_s",
                                        "diffusion_signature"} & rule.keys():
            from service.diagnosis.signatures import (
                RELAX_DIRECT_RATIO,
                RELAX_MIN_RATIO,
                RELAX_MIN_Z,
            )

            sig = (ev.signatures["diffusion_by_rest"][rest_key(rule["relax_rest_min_s"])]
                   if "relax_rest_min_s" in rule else ev.signatures["diffusion"])
            read = sig["statistic"] is not None
            z_ok = read and sig["z"] >= rule.get("relax_min_z", RELAX_MIN_Z)
            nominated = z_ok and sig["statistic"] >= rule.get("relax_min_ratio", RELAX_MIN_RATIO)
            direct = nominated and sig["statistic"] >= rule.get("relax_direct_ratio", RELAX_DIRECT_RATIO)
            c = _changed(c, evidence="direct" if direct else "nominated" if nominated else "fit",
                        fixed_reasons=_signature_requirement(c, nominated, read, rule))
        elif (c.name == "hysteresis" and not confirmation and HYSTERESIS_GRID.keys() & rule.keys()
              and "hysteresis" in ev.signatures):
            c = _changed(c, evidence=hysteresis_evidence(ev.signatures["hysteresis"], rule))
        out.append(c)
    return out


#: how the diffusion extension's plausibility reason begins (service.diagnosis.effects._diff_implausible)
DIFFUSION_TAU_REASON = "fitted surface lag τ "


def _tau_reasons(c: Candidate, min_tau_s: float) -> list[str]:
    """The diffusion candidate's fixed reasons with the surface-lag bound at ``min_tau_s``
    (:data:`service.diagnosis.effects.DIFFUSION_MIN_TAU_S` in the product)."""
    fixed = [r for r in c.fixed_reasons if not r.startswith(DIFFUSION_TAU_REASON)]
    if c.size < min_tau_s:
        fixed.append(f"{DIFFUSION_TAU_REASON}{c.size:.0f} s < {min_tau_s:g} s")
    return fixed


def _undetermined_reasons(c: Candidate, max_ln_std: float) -> list[str]:
    """The diffusion candidate's fixed reasons with the undetermined-lag bound at ``max_ln_std``
    (:data:`service.diagnosis.effects.DIFFUSION_MAX_LN_TAU_STD` in the product)."""
    from service.diagnosis.effects import DIFFUSION_UNDETERMINED_REASON

    fixed = [r for r in c.fixed_reasons if not r.startswith(DIFFUSION_UNDETERMINED_REASON)]
    if c.size_ln_std is not None and c.size_ln_std >= max_ln_std:
        fixed.append(f"{DIFFUSION_UNDETERMINED_REASON}{c.size_ln_std:.2f} >= {max_ln_std:g}")
    return fixed


def _capacity_reasons(c: Candidate, min_change: float | None) -> list[str]:
    """The capacity candidate's fixed reasons with the small-change bound at ``min_change`` (``None``:
    the product's :data:`service.diagnosis.effects.CAPACITY_MIN_CHANGE`).  Applied whether or not the
    rule names it: evidence diagnosed before the bound existed carries no such reason."""
    from service.diagnosis.effects import (
        CAPACITY_MIN_CHANGE,
        CAPACITY_SMALL_REASON,
        capacity_small_reason,
    )

    fixed = [r for r in c.fixed_reasons if not r.startswith(CAPACITY_SMALL_REASON)]
    why = capacity_small_reason(c.size, CAPACITY_MIN_CHANGE if min_change is None else min_change)
    return fixed if why is None else [*fixed, why]


def hysteresis_evidence(sig: dict, rule: dict[str, float]) -> str:
    """The hysteresis candidate's evidence class at ``rule``'s signature levels (a level not in it
    keeps the product's), as :func:`~service.diagnosis.signatures.rest_branch_offset` and
    :func:`~service.diagnosis.signatures.direction_offset` decide it: ``direct`` when the rest ends
    measure the half-gap, ``nominated`` when the direction state in the base residual does, else ``fit``."""
    from service.diagnosis import signatures as s

    min_gap = rule.get("branch_min_half_gap_v", s.BRANCH_MIN_HALF_GAP_V)
    branch = ((sig.get("n_rests") or 0) >= s.BRANCH_MIN_RESTS and sig.get("half_gap_v") is not None
              and s.branch_nominates(sig["statistic"], sig["half_gap_v"], sig["spread"], sig["relaxation"],
                                     rule.get("branch_min_z", s.BRANCH_MIN_Z), min_gap))
    direction = (sig.get("direction_z") is not None and sig.get("direction_half_gap_v") is not None
                 and s.direction_nominates(sig["direction_z"], sig["direction_half_gap_v"],
                                           rule.get("direction_min_z", s.DIRECTION_MIN_Z), min_gap))
    return "direct" if branch else "nominated" if direction else "fit"


def _signature_requirement(c: Candidate, nominated: bool, read: bool, rule: dict[str, float]) -> list[str]:
    """``c``'s fixed reasons with the pipeline's refusal of an effect that needs its signature
    (:func:`~service.diagnosis.effects.signature_refuses` at the effect's own requirement, or at
    ``rule``'s ``<effect>_signature`` level) set by whether the signature read anything and, at
    the rule's levels, nominated it."""
    from service.diagnosis.effects import EFFECTS, SIGNATURE_NEEDED, signature_refuses
    from service.diagnosis.pipeline import SIGNATURE_REQUIRED

    fixed = [r for r in c.fixed_reasons if not r.startswith(SIGNATURE_REQUIRED)]
    level = rule.get(f"{c.name}_signature")
    needed = EFFECTS[c.name].needs_signature if level is None else SIGNATURE_NEEDED[int(level)]
    if signature_refuses(needed, nominated, read):
        fixed.append(f"{SIGNATURE_REQUIRED}not nominated at this rule's signature levels")
    return fixed


def _changed(c: Candidate, **changes) -> Candidate:
    """A copy of ``c`` with ``changes`` (what :func:`dataclasses.replace` gives, without re-running
    ``__init__``: the rule search makes millions of these)."""
    out = object.__new__(Candidate)
    out.__dict__ = {**c.__dict__, **changes}
    return out


@functools.lru_cache(maxsize=64)
def _options(thresholds: tuple[tuple[str, float], ...]):
    """The pipeline's options at a rule's significance thresholds (one per rule, not per recording)."""
    from service.diagnosis.pipeline import DiagnoseOptions

    return replace(DiagnoseOptions(), **dict(thresholds))


def _judge(cands: Iterable[Candidate], noise_mv: float, opt) -> list[Candidate]:
    """The candidates with ``significant`` set under ``opt`` and ranked as the pipeline ranks them."""
    from service.diagnosis.pipeline import rank, significance_reasons

    judged = []
    for c in cands:
        reasons = significance_reasons(c.score, c.rmse_before_mv, c.rmse_after_mv, c.delta_bic, noise_mv,
                                       c.evidence, opt, c.measured)
        judged.append(_changed(c, significant=not reasons and not c.fixed_reasons))
    return rank(judged, opt.min_abs_gain_noise * noise_mv)


def decide(ev: Evidence, rule: dict[str, float]) -> tuple[str, Candidate | None]:
    """The verdict :func:`~service.diagnosis.pipeline.run_diagnosis` reaches on ``ev`` with the
    rule ``rule`` (significance thresholds and signature levels; a key left out keeps the value the
    diagnosis ran with), and the named candidate (with the figures of the split it was named on).
    A retry on the confirmation split is possible only for effects the diagnosis itself nominated
    or measured directly (their figures are the only ones there)."""
    from service.diagnosis.pipeline import SIGNATURE_REQUIRED, retry_candidates

    opt = _options(tuple(sorted((k, v) for k, v in rule.items() if k not in SIGNATURE_RULES)))
    ranked = _judge(_with_signature_rules(ev.candidates, ev, rule), ev.noise_mv, opt)
    if ranked and ranked[0].significant:
        return ranked[0].name, ranked[0]
    retry = set(retry_candidates(ranked))
    if retry and ev.confirm_noise_mv is not None:
        # a fit-part signature with nothing to read on the confirmation split keeps the first split's
        # nomination, and a direct effect needs the nominated bar there
        # (service.diagnosis.pipeline.confirm_nominated)
        unread = set(ev.signatures.get("confirm_unread", []))
        again = [replace(c, evidence="nominated", measured=c.evidence == "direct",
                         fixed_reasons=[r for r in c.fixed_reasons if not r.startswith(SIGNATURE_REQUIRED)])
                 if c.name in unread or c.evidence == "direct" else c
                 for c in _with_signature_rules([c for c in ev.confirm_candidates if c.name in retry], ev, rule,
                                                confirmation=True)]
        confirmed = [c for c in _judge(again, ev.confirm_noise_mv, opt) if c.significant and c.evidence == "nominated"]
        if confirmed:
            return confirmed[0].name, confirmed[0]
    return "none", None


#: a false alarm costs as much as this many missed or misnamed effects: a user acts on a named
#: effect.  Counting false alarms strictly first lets a cell whose clean recordings every rule
#: names (slow solid diffusion the base model lacks) decide between rules far apart in right verdicts.
FALSE_ALARM_COST = 5


@dataclass
class Tally:
    right: int = 0
    total: int = 0
    clean: int = 0
    false_alarms: int = 0

    def key(self) -> int:
        """Smaller is better: the verdicts wrong, a false alarm on a clean recording counted as
        :data:`FALSE_ALARM_COST` of them."""
        return self.total - self.right + (FALSE_ALARM_COST - 1) * self.false_alarms

    def __add__(self, other: Tally) -> Tally:
        return Tally(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))


def tally(evs: Sequence[Evidence], rule: dict[str, float]) -> Tally:
    t = Tally()
    for ev in evs:
        verdict, _ = decide(ev, rule)
        t.total += 1
        t.right += verdict == ev.effect
        if ev.effect == "none":
            t.clean += 1
            t.false_alarms += verdict != "none"
    return t


#: the axes whose steps :func:`_distance_to_default` counts (a rule on no axis here counts 1 when moved)
STEP_AXES: dict[str, tuple[float, ...]] = {**RULE_GRID, **HYSTERESIS_GRID, **DIRECT_DIFFUSION_GRID}


def _distance_to_default(rule: dict[str, float], now: dict[str, float]) -> float:
    """Grid steps from the product's current rule (the tie-break: move no further than needed)."""
    steps = 0.0
    for k, v in rule.items():
        grid = STEP_AXES.get(k, (v,))
        current = now.get(k, v)
        steps += abs(grid.index(v) - grid.index(current)) if v in grid and current in grid else float(v != current)
    return steps


#: rules per job when the search runs on several processes
TALLY_CHUNK = 400


def _tally_chunk(job: tuple[Sequence[Evidence], Sequence[dict[str, float]]]) -> list[dict[str, Tally]]:
    evs, rules = job
    by_cell: dict[str, list[Evidence]] = {}
    for ev in evs:
        by_cell.setdefault(ev.cell, []).append(ev)
    return [{c: tally(cell_evs, rule) for c, cell_evs in by_cell.items()} for rule in rules]


def tallies_by_cell(evs: Sequence[Evidence], grid: Sequence[dict[str, float]], progress=None,
                    jobs: int = 1) -> list[dict[str, Tally]]:
    """For each rule of ``grid``, its tally on each cell's recordings (computed once; a fold's
    training tally is the sum over its cells), on ``jobs`` processes."""
    chunks = [(evs, grid[k:k + TALLY_CHUNK]) for k in range(0, len(grid), TALLY_CHUNK)]
    parallel = jobs > 1 and len(chunks) > 1
    out: list[dict[str, Tally]] = []
    with ProcessPoolExecutor(max_workers=jobs) if parallel else contextlib.nullcontext() as pool:
        for part in (pool.map if parallel else map)(_tally_chunk, chunks):
            out.extend(part)
            if progress:
                progress(f"{len(out)}/{len(grid)} rules")
    return out


def _best(grid: Sequence[dict[str, float]], totals: Sequence[Tally]) -> tuple[dict[str, float], Tally]:
    now = current_rule()
    k = min(range(len(grid)), key=lambda j: (totals[j].key(), _distance_to_default(grid[j], now)))
    return grid[k], totals[k]


def choose_rule(evs: Sequence[Evidence], grid: Sequence[dict[str, float]],
                by_cell: list[dict[str, Tally]] | None = None, leave_out: str | None = None) -> tuple[dict[str, float], Tally]:
    """The rule with the fewest verdicts wrong on ``evs`` (without the cell ``leave_out``), a false
    alarm counted :data:`FALSE_ALARM_COST` times; ties go to the rule nearest the product's current one."""
    by_cell = by_cell if by_cell is not None else tallies_by_cell(evs, grid)
    totals = [sum((t for c, t in per.items() if c != leave_out), Tally()) for per in by_cell]
    return _best(grid, totals)


@dataclass
class Row:
    """One held-out recording's verdict under the rule chosen on the other cells."""

    stem: str
    cell: str
    effect: str
    level: str
    drive: str
    verdict: str
    cut: float | None  # held-out RMSE cut of the named effect (1 - after / before)
    excess_removed: float | None  # (before - after) / (before - twin's base held-out RMSE)
    # the effect's part of the base held-out RMSE, sqrt(base² - twin²), over the twin's (the model's
    # floor on that drive): below 1 the effect is smaller than what the base model misses anyway
    effect_to_floor: float | None = None
    # the cut the clean twin's floor leaves room for, 1 - twin / base held-out RMSE (0 when the
    # base is at or under the floor): what an extension that removed the whole effect would cut
    best_cut: float | None = None


def leave_one_cell_out(evs: Sequence[Evidence], grid: Sequence[dict[str, float]] | None = None,
                       progress=None, by_cell: list[dict[str, Tally]] | None = None) -> tuple[list[Row], dict[str, dict]]:
    """Rows scored with the rule chosen on the other cells, and per cell the rule and its
    training tally."""
    grid = grid if grid is not None else rule_grid()
    by_cell = by_cell if by_cell is not None else tallies_by_cell(evs, grid, progress)
    floors = {ev.stem: ev.base_rmse_heldout_mv for ev in evs if ev.effect == "none"}
    rows, chosen = [], {}
    for cell in dict.fromkeys(ev.cell for ev in evs):
        rule, t = choose_rule(evs, grid, by_cell, leave_out=cell)
        chosen[cell] = {"rule": rule, "train": asdict(t)}
        for ev in (ev for ev in evs if ev.cell == cell):
            verdict, named = decide(ev, rule)
            cut = excess = None
            if named is not None:
                cut = named.score
                floor = floors.get(f"{ev.cell}_none_clean_{ev.drive}")
                if floor is not None and named.rmse_before_mv > floor:
                    excess = (named.rmse_before_mv - named.rmse_after_mv) / (named.rmse_before_mv - floor)
            floor = floors.get(f"{ev.cell}_none_clean_{ev.drive}")
            visible = best = None
            if floor and ev.effect != "none":
                visible = math.sqrt(max(ev.base_rmse_heldout_mv**2 - floor**2, 0.0)) / floor
                best = max(1.0 - floor / ev.base_rmse_heldout_mv, 0.0)
            rows.append(Row(ev.stem, ev.cell, ev.effect, ev.level, ev.drive, verdict, cut, excess, visible, best))
    return rows, chosen


def _pct(a: int, b: int) -> str:
    return f"{a}/{b} ({100 * a / b:.0f} %)" if b else "0/0"


def _visibility_lines(effect_rows: Sequence[Row]) -> list[str]:
    """Per truth: how large the effect is against the clean twin's floor, for the recordings named
    right and for the ones missed (named ``none``)."""
    out = [("How large each effect is against the model's floor (its part of the base held-out RMSE over the "
            "clean twin's; median, with the share below 1):"), "",
           "| truth | named right | missed (none) |", "|---|---|---|"]

    def cell(rs: list[Row]) -> str:
        v = [r.effect_to_floor for r in rs if r.effect_to_floor is not None]
        return f"{statistics.median(v):.2f} ({sum(x < 1 for x in v)}/{len(v)} below 1)" if v else "–"

    for t in dict.fromkeys(r.effect for r in effect_rows):
        rs = [r for r in effect_rows if r.effect == t]
        out.append(f"| {t} | {cell([r for r in rs if r.verdict == t])} | {cell([r for r in rs if r.verdict == 'none'])} |")
    return out


def report(rows: Sequence[Row], chosen: dict[str, dict], pooled_rule: dict[str, float]) -> str:
    """Markdown: per-cell results and rules, the pooled confusion matrix, false alarms, detection by
    level and drive, and the named effects' held-out cuts."""
    truths = [e for e in EFFECTS if any(r.effect == e for r in rows)]
    verdicts = truths + sorted({r.verdict for r in rows} - set(truths))
    out = ["| held-out cell | right | clean: false alarms | rule chosen on the other cells |", "|---|---|---|---|"]
    for cell, info in chosen.items():
        mine = [r for r in rows if r.cell == cell]
        clean = [r for r in mine if r.effect == "none"]
        rule = ", ".join(f"{k}={v:g}" for k, v in info["rule"].items())
        out.append(f"| {cell} | {_pct(sum(r.verdict == r.effect for r in mine), len(mine))} | "
                   f"{sum(r.verdict != 'none' for r in clean)}/{len(clean)} | {rule} |")
    clean = [r for r in rows if r.effect == "none"]
    effect_rows = [r for r in rows if r.effect != "none"]
    out += ["", (f"**Pooled over held-out cells: {_pct(sum(r.verdict == r.effect for r in rows), len(rows))} right; "
                f"false alarms on clean recordings {sum(r.verdict != 'none' for r in clean)}/{len(clean)}; effects "
                f"named as another effect {sum(r.verdict not in ('none', r.effect) for r in effect_rows)}/"
                f"{len(effect_rows)}.**"), "",
            "Confusion matrix, pooled (rows: truth, columns: verdict):", "",
            "| truth | " + " | ".join(verdicts) + " |", "|---|" + "---|" * len(verdicts)]
    for t in truths:
        counts = Counter(r.verdict for r in rows if r.effect == t)
        out.append(f"| {t} | " + " | ".join(str(counts.get(v, 0) or "") for v in verdicts) + " |")
    out += ["", "Per cell (right / recordings, by truth):", "",
            "| cell | " + " | ".join(truths) + " |", "|---|" + "---|" * len(truths)]
    for cell in chosen:
        cells = []
        for t in truths:
            rs = [r for r in rows if r.cell == cell and r.effect == t]
            cells.append(f"{sum(r.verdict == t for r in rs)}/{len(rs)}")
        out.append(f"| {cell} | " + " | ".join(cells) + " |")
    out += ["", "Detection by level and by drive (effect recordings named right):", "",
            "| level | right |", "|---|---|"]
    for lv in LEVELS:
        rs = [r for r in effect_rows if r.level == lv]
        out.append(f"| {lv} | {_pct(sum(r.verdict == r.effect for r in rs), len(rs))} |")
    out += ["", "| drive | right (effects) | clean false alarms |", "|---|---|---|"]
    for d in DRIVES:
        rs = [r for r in effect_rows if r.drive == d]
        cs = [r for r in clean if r.drive == d]
        out.append(f"| {d} | {_pct(sum(r.verdict == r.effect for r in rs), len(rs))} | "
                   f"{sum(r.verdict != 'none' for r in cs)}/{len(cs)} |")
    cuts = [r.cut for r in effect_rows if r.verdict == r.effect and r.cut is not None]
    excess = [r.excess_removed for r in effect_rows if r.verdict == r.effect and r.excess_removed is not None]
    out += ["", (f"Named right: median held-out RMSE cut {_median_pct(cuts)} (n = {len(cuts)}); median share of the "
                f"effect's part of the held-out RMSE removed, against the clean twin's floor, {_median_pct(excess)} "
                f"(n = {len(excess)})."),
            "", _best_cut_line(effect_rows),
            "", *_visibility_lines(effect_rows),
            "", "Rule chosen on all cells (the product's default): "
            + ", ".join(f"`{k}` = {v:g}" for k, v in pooled_rule.items()) + "."]
    return "\n".join(out)


def _best_cut_line(effect_rows: Sequence[Row]) -> str:
    """The median cut the clean twins' floors leave room for: the ceiling of the median cut for
    extensions of this base model that take none of its model-form error."""
    right = [r.best_cut for r in effect_rows if r.verdict == r.effect and r.best_cut is not None]
    every = [r.best_cut for r in effect_rows if r.best_cut is not None]
    return (f"The cut the clean twin's floor leaves room for (1 − twin's base held-out RMSE / the recording's): median "
            f"{_median_pct(right)} where named right (n = {len(right)}), {_median_pct(every)} over every effect "
            f"recording (n = {len(every)}).")


def _median_pct(xs: Sequence[float]) -> str:
    return f"{100 * statistics.median(xs):.0f} %" if xs else "-"


def load_evidence(workdir: Path) -> list[Evidence]:
    return [Evidence.from_json(json.loads(p.read_text())) for p in sorted(workdir.glob("*.evidence.json"))]


# -- command line ----------------------------------------------------------------------------------
def _run_jobs(fn, jobs_args: Sequence[tuple], jobs: int, what: str) -> None:
    from rich.progress import Progress

    with Progress(transient=False) as bar, ProcessPoolExecutor(max_workers=max(1, jobs)) as pool:
        task = bar.add_task(what, total=len(jobs_args))
        for stem, status in pool.map(fn, jobs_args):
            bar.console.print(f"{stem}: {status}")
            bar.advance(task)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.devset", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage", choices=("build", "evidence", "labelled", "rules", "plan"),
                    help="build: simulate the recordings; evidence: diagnose each once; labelled: diagnose the "
                         "labelled files of --labelled likewise (into --labelled-workdir); rules: the leave-one-cell-out "
                         "rule search and its report (the labelled files' evidence, when there, joins their cell's "
                         "recordings); plan: list the recordings")
    ap.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR, help="the set's cache (default: %(default)s)")
    ap.add_argument("--cells", default=",".join(CELLS), help="PyBaMM parameter sets (default: %(default)s)")
    ap.add_argument("--jobs", type=int, default=1,
                    help="recordings simulated or diagnosed at once, or processes the rule search runs on (default 1)")
    ap.add_argument("--labelled", type=Path, default=LABELLED_DATA,
                    help="the labelled synthetic recordings (default: %(default)s)")
    ap.add_argument("--labelled-workdir", type=Path, default=DEFAULT_WORKDIR / "labelled",
                    help="their evidence (default: %(default)s)")
    ap.add_argument("--json", type=Path, help="rules: write the rows and chosen rules as JSON")
    ap.add_argument("--markdown", type=Path, help="rules: write the report as Markdown")
    ap.add_argument("--search-requirement", action="store_true",
                    help="rules: search also whether diffusion needs its relaxation signature (a structural rule "
                         "the product fixes; this asks what the search itself would choose per held-out cell)")
    ap.add_argument("--wide-grid", action="store_true",
                    help="rules: search the axes whose choice sits at an edge of the grid past that edge "
                         "(WIDE_GRID), to check the choice is not held by the edge")
    ap.add_argument("--diffusion-signature", type=float, choices=REQUIREMENT_GRID["diffusion_signature"],
                    help="rules: hold the requirement at this level (0 never, 1 where read, 2 always) instead of "
                         "the product's, to compare the levels")
    ap.add_argument("--search-rest-length", action="store_true",
                    help="rules: search also the shortest rest the diffusion relaxation signature reads "
                         "(60, 120, 300, 500 s; the product reads 500 s)")
    ap.add_argument("--search-hysteresis", action="store_true",
                    help="rules: search also the hysteresis signatures' levels (the rest ends' z and half-gap, the "
                         "direction state's z; evidence diagnosed before these were kept keeps its classes)")
    ap.add_argument("--search-lag-bound", action="store_true",
                    help="rules: search also the shortest surface lag a fitted diffusion may have (30, 60, 120 s; "
                         "the product's is 60 s; evidence diagnosed before the lag was kept keeps its refusals)")
    ap.add_argument("--search-lag-std", action="store_true",
                    help="rules: search also how well the fit part must determine a fitted diffusion lag's time "
                         "constant (σ of ln τ below 0.75, 1, 1.5 or no bound; the product's is 1)")
    ap.add_argument("--search-direct-diffusion", action="store_true",
                    help="rules: search also the relaxation ratio from which the signature measures slow diffusion "
                         "directly (inf = never, the product's; 0.25, 0.35, 0.5)")
    ap.add_argument("--product-rule", action="store_true",
                    help="rules: search nothing, hold every rule at the product's value: how socd diagnose as it "
                         "ships reads these cells (a set no rule was chosen on, e.g. other --cells in another "
                         "--workdir)")
    ap.add_argument("--hold", action="append", default=[], metavar="RULE=VALUE",
                    help="rules: search only the rules with RULE at VALUE, e.g. relax_rest_min_s=500 (a level held "
                         "for every fold, to compare it with the one the search chooses); repeatable")
    args = ap.parse_args(argv)
    held = _parse_holds(ap, args.hold)
    cells = [c for c in args.cells.split(",") if c]
    specs = plan(cells)
    if args.stage == "plan":
        for s in specs:
            print(s.stem, s.seed)
        print(f"{len(specs)} recordings", file=sys.stderr)
        return 0
    args.workdir.mkdir(parents=True, exist_ok=True)
    if args.stage == "build":
        from research.validate_pybamm import _pybamm

        _pybamm()
        _run_jobs(build_one, [(s, str(args.workdir)) for s in specs], args.jobs, "simulating")
        return 0
    if args.stage == "evidence":
        _run_jobs(evidence_one, [(s, str(args.workdir)) for s in specs], args.jobs, "diagnosing")
        return 0
    if args.stage == "labelled":
        if not (args.labelled / "labels.json").is_file():
            ap.error(f"--labelled {args.labelled}: no labels.json there")
        args.labelled_workdir.mkdir(parents=True, exist_ok=True)
        stems = sorted(json.loads((args.labelled / "labels.json").read_text()))
        _run_jobs(labelled_one, [(st, str(args.labelled), str(args.labelled_workdir)) for st in stems], args.jobs,
                  "diagnosing the labelled files")
        return 0
    evs = [ev for ev in load_evidence(args.workdir) if ev.cell in cells]
    if len({ev.cell for ev in evs}) < 2:
        ap.error(f"{args.workdir}: evidence for fewer than two cells; run the build and evidence stages first")
    for ev in evs:
        _complete(ev, args.workdir / f"{ev.stem}.csv", json.loads((args.workdir / f"{ev.stem}.json").read_text())["capacity_ah"])
    labelled = load_evidence(args.labelled_workdir) if args.labelled_workdir.is_dir() else []
    labels = json.loads((args.labelled / "labels.json").read_text()) if labelled else {}
    for ev in labelled:
        _complete(ev, args.labelled / f"{ev.stem}.csv",
                  json.loads((args.labelled / f"{ev.stem}.meta.json").read_text())["capacity_ah"])
        ev.cell = set_cell(labels.get(ev.stem, {}).get("cell", ev.cell), cells)
    grid = rule_grid(args.search_requirement, args.wide_grid, args.search_rest_length, args.search_hysteresis,
                     args.search_lag_bound, args.search_direct_diffusion, args.search_lag_std)
    if args.diffusion_signature is not None and not args.search_requirement:
        grid = [{**r, "diffusion_signature": args.diffusion_signature} for r in grid]
    if args.product_rule:
        grid = product_rule_grid(grid)
    grid = [r for r in grid if all(r.get(k) == v for k, v in held.items())]
    if not grid:
        ap.error(f"--hold {' '.join(args.hold)}: no rule of the grid searched holds that (--wide-grid adds "
                 "values; --search-rest-length, --search-hysteresis, --search-lag-bound, --search-lag-std and --search-direct-diffusion "
                 "add the rules they name)")
    doc = search([*evs, *labelled], grid, progress=lambda msg: print(msg, file=sys.stderr), jobs=args.jobs)
    held_out = {r["stem"]: r["verdict"] for r in doc["rows"]}
    doc["labelled"] = [{"stem": ev.stem, "cell": ev.cell, "truth": ev.effect, "verdict": held_out[ev.stem],
                        "verdict_before": decide(ev, {})[0]} for ev in labelled]
    text = markdown(doc)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))
    return 0


def _parse_holds(ap: argparse.ArgumentParser, holds: Sequence[str]) -> dict[str, float]:
    """``--hold RULE=VALUE`` options as a dict; an unknown rule or a value off its grid is an error."""
    axes = rule_axes(with_requirement=True, wide=True, with_rest_length=True, with_hysteresis=True, with_lag_bound=True,
                     with_direct_diffusion=True, with_lag_std=True)
    out = {}
    for h in holds:
        key, _, value = h.partition("=")
        axis = axes.get(key)
        try:
            v = float(value)
        except ValueError:
            ap.error(f"--hold {h}: VALUE must be a number")
        if axis is None:
            ap.error(f"--hold {h}: unknown rule {key!r}; rules: {', '.join(axes)}")
        if v not in axis:
            ap.error(f"--hold {h}: {v:g} is not on the grid of {key} ({', '.join(f'{a:g}' for a in axis)})")
        out[key] = v
    return out


def set_cell(name: str, cells: Sequence[str]) -> str:
    """The set's spelling of a labelled file's cell (``okane2022`` is ``OKane2022``), so the file is
    held out with its cell; a cell the set does not have is a fold of its own."""
    return next((c for c in cells if c.lower() == name.lower()), name)


def _complete(ev: Evidence, csv: Path, capacity_ah: float) -> None:
    """Evidence cached before the signature statistics were kept gets them from its recording (they
    read the recording alone, no fit)."""
    from service.diagnosis.pipeline import DiagnoseOptions
    from service.recording import load_recording

    if "confirm_unread" not in ev.signatures or (ev.signatures.get("temperature") or {}).get("coldest_c") is None:
        ev.signatures = recording_signature_stats(load_recording(csv), capacity_ah, DiagnoseOptions())
    elif "diffusion_by_rest" not in ev.signatures:
        ev.signatures["diffusion_by_rest"] = relaxation_by_rest(load_recording(csv), capacity_ah, DiagnoseOptions())


def search(evs: Sequence[Evidence], grid: Sequence[dict[str, float]] | None = None, progress=None,
           jobs: int = 1) -> dict:
    """The leave-one-cell-out rows, the rule per held-out cell, the rule chosen on every cell and
    its in-sample tally, and the diagnosis run times, as the ``rules`` stage writes them."""
    grid = grid if grid is not None else rule_grid()
    by_cell = tallies_by_cell(evs, grid, progress, jobs)
    rows, chosen = leave_one_cell_out(evs, grid, by_cell=by_cell)
    pooled_rule, pooled = choose_rule(evs, grid, by_cell)
    seconds = [ev.seconds_chronological + ev.seconds_confirmation for ev in evs]
    return {"rows": [asdict(r) for r in rows], "chosen": chosen, "pooled_rule": pooled_rule,
            "pooled": asdict(pooled), "rules_searched": len(grid), "recordings": len(evs),
            "seconds": sorted(seconds), "ambient_margin": ambient_margin(evs)}


def ambient_off_nominal_k(ev: Evidence) -> float | None:
    """How far the recording says its ambient is from the nominal one, as the temperature signature
    reads it: its opening temperature's distance from the nominal ambient, or how far it cools below."""
    t = ev.signatures.get("temperature") or {}
    if t.get("nominal_c") is None or t.get("coldest_c") is None:
        return None
    return max(abs(t["opening_c"] - t["nominal_c"]), t["nominal_c"] - t["coldest_c"])


def ambient_margin(evs: Sequence[Evidence]) -> dict | None:
    """The largest :func:`ambient_off_nominal_k` of a recording whose ambient did not change and the
    smallest of one whose ambient did, with their stems: the room the temperature signature's
    5 K level has on the set."""
    pairs = [(ambient_off_nominal_k(ev), ev) for ev in evs]
    without = [(k, ev.stem) for k, ev in pairs if k is not None and ev.effect != "temperature"]
    with_ = [(k, ev.stem) for k, ev in pairs if k is not None and ev.effect == "temperature"]
    if not without or not with_:
        return None
    (k_out, s_out), (k_in, s_in) = max(without), min(with_)
    return {"without_k": round(k_out, 2), "without_stem": s_out, "with_k": round(k_in, 2), "with_stem": s_in}


def markdown(doc: dict) -> str:
    """The report of a :func:`search` (or its JSON)."""
    rows = [Row(**r) for r in doc["rows"]]
    pooled = doc["pooled"]
    sec = doc["seconds"]
    return (report(rows, doc["chosen"], doc["pooled_rule"])
            + f" In-sample with that rule: {pooled['right']}/{pooled['total']} right, false alarms "
              f"{pooled['false_alarms']}/{pooled['clean']} ({doc['rules_searched']} rules searched)."
            + f"\n\nDiagnosis run time per recording with the default rule (the retry included where it runs): "
              f"median {statistics.median(sec):.0f} s, 90th percentile {sec[int(0.9 * (len(sec) - 1))]:.0f} s, "
              f"longest {sec[-1]:.0f} s ({len(sec)} recordings, two diagnosed at once on two cores)."
            + _ambient_line(doc.get("ambient_margin"))
            + _labelled_line(doc.get("labelled", [])))


def _ambient_line(margin: dict | None) -> str:
    from service.diagnosis.signatures import OPENING_TEMP_K

    if not margin:
        return ""
    return (f"\n\nThe temperature signature's level ({OPENING_TEMP_K:g} K from the nominal ambient, at the opening or "
            f"below it) on the set: the recording without an ambient change that comes closest reads "
            f"{margin['without_k']:.1f} K (`{margin['without_stem']}`); the recording with one that comes least "
            f"far reads {margin['with_k']:.1f} K (`{margin['with_stem']}`).")


def _labelled_line(labelled: Sequence[dict]) -> str:
    """The labelled files' verdicts held out with their cell (under the rule chosen on the others)."""
    if not labelled:
        return ""
    right = sum(d["verdict"] == d["truth"] for d in labelled)
    before = sum(d["verdict_before"] == d["truth"] for d in labelled)
    cells = ", ".join(sorted({d.get("cell", "?") for d in labelled}))
    wrong = ", ".join(f"{d['stem']} ({d['truth']} named {d['verdict']})" for d in labelled if d["verdict"] != d["truth"])
    return (f"\n\nThe labelled files (`../shared/data/synthetic`, in the rows above with their cell, {cells}), held "
            f"out with it: {right}/{len(labelled)} right (the rule before: {before}/{len(labelled)})"
            + (f"; wrong: {wrong}." if wrong else "."))


if __name__ == "__main__":
    raise SystemExit(main())
