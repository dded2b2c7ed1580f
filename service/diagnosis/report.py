"""Markdown report with PNG plots for a :class:`~service.diagnosis.pipeline.Diagnosis`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.cell.units import SECONDS_PER_HOUR
from service.diagnosis.effects import EFFECTS, Context


def _branch_lines(b: dict) -> list[str]:
    """The hysteresis signature in words (signatures.rest_branch_offset)."""
    return [(f"Rest-end branch offset: {len(b['rest_end_s'])} rests of at least {b['min_rest_s']:.0f} s after load give a half-gap "
            f"U_H = {1000 * b['half_gap_v']:+.2f} ± {1000 * b['half_gap_se_v']:.2f} mV (z {b['statistic']:g}; "
            f"direction-state rate {b['rate']:g}; SOC at the start {b['soc0']:.3f}); residual spread "
            f"{100 * b['spread']:.0f} % of U_H, relaxation left at the rest ends {100 * b['relaxation']:.0f} % of U_H. "
            f"Rule: z ≥ {b['threshold']:g}, U_H ≥ {1000 * b['min_half_gap_v']:g} mV, spread ≤ "
            f"{100 * b['max_spread']:.0f} %, relaxation ≤ {100 * b['max_relaxation']:.0f} %. These rest ends are "
            "left out of every held-out score."), ""]


def _direction_lines(d: dict) -> list[str]:
    """The drive-cycle hysteresis test in words (signatures.direction_offset)."""
    return [(f"Direction state in the base residual (drive cycles): beyond the C-rate and its low-passes, the Eq.-1 "
             f"direction state (rate {d['rate']:g}) explains a half-gap of {1000 * d['half_gap_v']:+.2f} ± "
             f"{1000 * d['half_gap_se_v']:.2f} mV (z {d['statistic']:g}, τ_int {d['tau_int']:g} samples, "
             f"{d['n_samples']} fit-part samples, high-passed). Rule: z ≥ {d['threshold']:g} and U_H ≥ "
             f"{1000 * d['min_half_gap_v']:g} mV; it nominates hysteresis (the 10 % bar), it does not measure it"
             + (" — **nominated here**." if d["nominated"] else ".")), ""]


def _confirmation_lines(dg) -> list[str]:
    """The protocol line for the second look at a nominated effect (pipeline.confirm_nominated)."""
    c = dg.protocol.get("confirmation")
    if not c:
        return []
    got = ", ".join(c["confirmed"]) or "none of them"
    line = (f"- Confirmation: the verdict on this split was none while a signature nominated "
            f"{', '.join(c['effects'])}; refitted with a fresh base on the {c['split']} split (base held-out "
            f"{c['base_rmse_heldout_mv']:.2f} mV over {c['heldout_samples']} samples, {c['seconds']:.0f} s): "
            f"cleared its bar there: {got}. A confirmed effect's row above carries that split's figures.")
    return [line]


def _relaxation_lines(r: dict) -> list[str]:
    """The diffusion signature in words (signatures.rest_relaxation)."""
    rests = ", ".join(f"{rem:+.1f}/{step:.1f} mV" for rem, step in zip(r["remaining_mv"], r["step_mv"]))
    return [(f"Relaxation at rest ends: {r['n_rests']} rests of at least {r['min_rest_s']:.0f} s after a load step of "
             f"at least {r['min_step_c']:g}C in the fit part; relaxation still to come (diffusion tail 2·t·dV/dt) over "
             f"the ohmic step when the current stopped: {rests}; median ratio {r['statistic']:g}, pooled z "
             f"{r['z']:g}. Rule: ratio ≥ {r['threshold']:g} and z ≥ {r['min_z']:g} (a healthy cell has done nearly "
             "all its relaxing after ten minutes). It nominates diffusion; it does not size the extension."), ""]


def _kinetics_lines(k: dict) -> list[str]:
    """The current-step kinetics signature in words (signatures.step_kinetics)."""
    return [(f"Current steps: {k['n_steps']} steps of at least {k['min_step_c']:g}C in the fit part (up to "
             f"{k['peak_c']:.2f}C); the voltage across them curves with the current as a Butler-Volmer term with an "
             f"apparent exchange current of {k['i0_c']:.3f}C (95 % upper bound {k['i0_upper_c']:.3f}C) beside a "
             f"linear {1000 * k['r_step_ohm']:.1f} mΩ (step residual RMS {k['rms_mv']:.2f} mV). Rule: upper bound "
             f"< {k['threshold']:g}C, the healthy-cell bound the kinetics extension's own size must also meet. "
             "It nominates kinetics; it does not size the extension."), ""]


def _capacity_lines(c: dict) -> list[str]:
    """The two-point capacity check in words."""
    lo, hi = c["capacity_scale_range"]
    return [(f"Two-point capacity: SOC {c['soc_start']:.3f} (range {c['soc_start_range'][0]:.3f}-"
            f"{c['soc_start_range'][1]:.3f}) at {c['t_start_s']:.0f} s and {c['soc_end']:.3f} "
            f"({c['soc_end_range'][0]:.3f}-{c['soc_end_range'][1]:.3f}) at {c['t_end_s']:.0f} s on the OCV table "
            f"(overpotential there {c['overpotential_start_mv']:+.1f} / {c['overpotential_end_mv']:+.1f} mV, "
            f"{c['ohmic_end_mv']:+.1f} mV of it ohmic), {100 * c['drawn_soc']:.1f} % of the stated capacity "
            f"drawn between them: capacity × {c['capacity_scale']:.3f} (range {lo:.3f}-{hi:.3f}); rule: the whole "
            f"range ≥ {100 * c['threshold']:.0f} % from 1 and the points ≥ {c['min_span_soc']:.1f} SOC apart. "
            "The end sample's voltage is read here, so no held-out score includes it."), ""]


def _fmt(v: float | None) -> str:
    if v is None:
        return "–"
    if v == 0 or not np.isfinite(v):
        return f"{v:g}"
    a = abs(v)
    return f"{v:.4g}" if 1e-3 <= a < 1e5 else f"{v:.3e}"


def _plots(dg, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec = dg.recording
    t_h = (rec.time_s - rec.time_s[0]) / SECONDS_PER_HOUR
    r_base = (rec.voltage_v - dg.v_base) * 1000
    top = dg.effects[0] if dg.effects else None
    shown = next((e for e in dg.effects if e.name == dg.verdict), top)
    files = []

    # 1. residual over time with the located windows and the split
    fig, ax = plt.subplots(figsize=(10, 3.8))
    ax.plot(t_h, r_base, lw=0.6, color="tab:red", label="base model")
    if shown is not None:
        ax.plot(t_h, (rec.voltage_v - shown.v_sim) * 1000, lw=0.6, color="tab:blue", alpha=0.8,
                label=f"with {shown.name}")
    for w in dg.located_full["windows"]:
        if w["flagged"]:
            ax.axvspan((w["t_start_s"] - rec.time_s[0]) / SECONDS_PER_HOUR, (w["t_end_s"] - rec.time_s[0]) / SECONDS_PER_HOUR,
                       color="orange", alpha=0.25, lw=0)
    ax.axvline((dg.protocol["t_split_s"] - rec.time_s[0]) / SECONDS_PER_HOUR, color="k", ls="--", lw=1)
    ax.text((dg.protocol["t_split_s"] - rec.time_s[0]) / SECONDS_PER_HOUR, ax.get_ylim()[1], " held out ->", va="top")
    ax.set_xlabel("time, h")
    ax.set_ylabel("measured - simulated, mV")
    ax.set_title("Residual over time (shaded: windows where it concentrates)")
    ax.legend(loc="lower left")
    fig.tight_layout()
    fig.savefig(out / "residual_time.png", dpi=110)
    plt.close(fig)
    files.append("residual_time.png")

    # 2. residual against the key feature of the top effect
    if top is not None:
        ctx = Context(
            time_s=rec.time_s, current_a=rec.current_a, temperature_c=rec.temperature_c,
            residual_v=rec.voltage_v - dg.v_base, soc=dg.soc_base,
            ocv_slope=dg.base_profile.ocv_table().slope(dg.soc_base, rec.temperature_c),
            capacity_ah=dg.base_profile.capacity_ah, ref_temp_c=float(dg.base["point"]["temp_c"]),
            soc_range=(0.0, 1.0), base_tau_df_s=100.0, base_r_sum_ohm=0.0,
        )
        label, feat = EFFECTS[top.name].feature(ctx)
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        step = max(1, feat.size // 5000)
        ax.scatter(feat[::step], r_base[::step], s=3, alpha=0.4, color="tab:red", label="base model")
        ax.scatter(feat[::step], ((rec.voltage_v - top.v_sim) * 1000)[::step], s=3, alpha=0.4, color="tab:blue",
                   label=f"with {top.name}")
        ax.set_xlabel(label)
        ax.set_ylabel("residual, mV")
        ax.set_title(f"Residual against the {top.name} feature")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "residual_feature.png", dpi=110)
        plt.close(fig)
        files.append("residual_feature.png")

    # 3. before/after overlay on the held-out part
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    h = dg.held_mask
    axes[0].plot(t_h[h], rec.voltage_v[h], color="k", lw=0.8, label="measured")
    axes[0].plot(t_h[h], dg.v_base[h], color="tab:red", lw=0.7, label="base model")
    if shown is not None:
        axes[0].plot(t_h[h], shown.v_sim[h], color="tab:blue", lw=0.7, label=f"with {shown.name}")
    axes[0].set_ylabel("voltage, V")
    axes[0].legend(loc="lower left")
    axes[0].set_title("Held-out part: measured vs simulated")
    axes[1].plot(t_h[h], r_base[h], color="tab:red", lw=0.6)
    if shown is not None:
        axes[1].plot(t_h[h], (rec.voltage_v[h] - shown.v_sim[h]) * 1000, color="tab:blue", lw=0.6)
    axes[1].set_ylabel("residual, mV")
    axes[1].set_xlabel("time, h")
    fig.tight_layout()
    fig.savefig(out / "overlay_heldout.png", dpi=110)
    plt.close(fig)
    files.append("overlay_heldout.png")

    # 4. evidence per effect
    fig, ax = plt.subplots(figsize=(7, 3.5))
    names = [e.name for e in dg.effects]
    scores = [100 * e.score for e in dg.effects]
    colors = ["tab:green" if e.significant else "tab:gray" for e in dg.effects]
    ax.barh(names[::-1], scores[::-1], color=colors[::-1])
    ax.axvline(100 * dg.thresholds["min_rel_gain"], color="k", ls="--", lw=1)
    ax.set_xlabel("held-out RMSE gain, %")
    ax.set_xlim(left=max(min(scores + [0]) - 5, -100))
    ax.set_title("Evidence per candidate (green: significant)")
    fig.tight_layout()
    fig.savefig(out / "evidence.png", dpi=110)
    plt.close(fig)
    files.append("evidence.png")
    return files


def write_report(dg, out_dir: str | Path) -> Path:
    """Write ``report.md`` and its PNGs to ``out_dir``; return the markdown path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = _plots(dg, out)
    th = dg.thresholds
    lines = [
        f"# socd diagnose: `{dg.recording.path.name}`",
        "",
        f"**Verdict: `{dg.verdict}`**" + (
            "" if dg.verdict == "none" else
            f" — held-out voltage RMSE {dg.effects[0].rmse_before_mv:.2f} → {dg.effects[0].rmse_after_mv:.2f} mV"
            f" ({100 * dg.effects[0].score:.1f} % lower)"),
        "",
        f"What it means ({dg.assessment.get('state', '')}): {dg.assessment.get('text', '')}.",
        "",
        "## Protocol",
        (f"- Split: chronological; the first {100 * dg.protocol['fit_fraction']:.0f} % of the duration "
         f"(up to t = {dg.protocol['t_split_s']:.0f} s) is fitted" if dg.protocol["split"] == "chronological" else
         "- Split: alternating blocks of about 10 min; every second block is held out"
         if dg.protocol["split"] == "blocks" else
         "- Split: interleaved; the duration is cut into 10 blocks and blocks 2, 4, 7, 9 are held out")
        + f" ({dg.protocol['fit_samples']} samples fitted, {dg.protocol['heldout_samples']} held out). The model "
        "runs through the whole recording; only the scored samples differ.",
        (f"- Initial state: {dg.protocol['initial_state']}; SOC0 = {dg.base['soc0']:.3f} "
        f"from {dg.base['v_rest0']:.4f} V."),
        ("- Every model is fitted at the recording's own rate; held-out RMSEs come from "
        "`service.cell.trajectory.simulate` on the saved profiles (the model `socd evaluate` runs)."),
        (f"- Significance (all required): held-out gain ≥ {100 * th['min_rel_gain']:.0f} % "
        f"({100 * th.get('min_rel_gain_nominated', th['min_rel_gain']):.0f} % for an effect its own signature "
        f"nominates: {', '.join(k for k, v in dg.signatures.items() if v.get('nominated')) or 'none here'}); "
        f"held-out RMSE drop ≥ "
        f"{th['min_abs_gain_noise']:g} × voltage noise ({th['noise_sigma_mv']:.2f} mV, from rests) = "
        f"{th['min_abs_gain_mv']:.2f} mV; ΔBIC ≥ {th['min_delta_bic']:g} on the fit part with "
        f"n_eff = {dg.base['n_eff']:.0f} (n / τ_int, τ_int = {dg.base['tau_int_samples']:.1f} samples). "
        f"An effect whose signature measures it directly (current_bias: the rest current; capacity: the "
        f"two-point check; hysteresis: the branch offset at the ends of long rests) needs only that its held-out "
        f"RMSE does not rise by more than the larger of {th.get('direct_max_rise_noise', 0.0):g} × voltage noise "
        f"and {100 * th.get('direct_max_rise_rel', 0.0):.0f} % of its base value = {th.get('direct_max_rise_mv', 0.0):.2f} mV."),
        (f"- Size: a fitted term the size of a healthy cell's is no departure and is not significant (kinetics: "
         f"exchange current ≥ {th.get('kinetics_max_i0_c', 0.1):g}C; diffusion: surface lag τ < "
         f"{th.get('diffusion_min_tau_s', 60.0):.0f} s, which relaxes within three minutes; capacity: a scale "
         f"within {100 * th.get('capacity_min_change', 0.0):g} % of the stated capacity)."),
        (f"- Ranking: a significant effect its signature measured directly goes before every fitted one; among the "
         f"rest, held-out RMSEs within {th['min_abs_gain_mv']:.2f} mV of the best are tied (the voltage cannot tell "
         "them apart), and a tie goes to one its signature nominated, then to the higher ΔBIC."),
        *_confirmation_lines(dg),
        "",
        "## Signatures (evidence outside the voltage fit)",
        "",
        "| effect | nominated | statistic | threshold | what |",
        "|---|---|---|---|---|",
        *[(f"| {k} | {'by the drive-cycle test below' if v.get('nominated_by') else '**yes**' if v.get('nominated') else 'no'} "
           f"| {v.get('statistic')} | {v.get('threshold')} | {v.get('what', '')} |") for k, v in dg.signatures.items()],
        *([(f"| hysteresis (drive cycle) | {'**yes**' if d['nominated'] else 'no'} | {d.get('statistic')} | "
            f"{d.get('threshold')} | {d.get('what', '')} |")]
          if (d := dg.signatures.get("hysteresis", {}).get("direction")) else []),
        "",
        *([(f"Rest current (true current 0): {1000 * dg.signatures['current_bias']['offset_a']:+.2f} ± "
           f"{1000 * dg.signatures['current_bias']['se_a']:.2f} mA over {dg.signatures['current_bias']['n_rests']} "
           f"rests ({dg.signatures['current_bias']['n_rest_samples']} samples), a Coulomb-count drift of "
           f"{100 * dg.signatures['current_bias']['drift_soc']:.2f} % SOC over the recording; rule: |z| ≥ "
           f"{dg.signatures['current_bias']['threshold']:g}, drift ≥ "
           f"{100 * dg.signatures['current_bias']['min_drift_soc']:.1f} % SOC and |offset| ≥ "
           f"{100 * dg.signatures['current_bias']['min_frac_1c']:.2f} % of 1C."), ""]
          if dg.signatures.get("current_bias", {}).get("se_a") else []),
        *([(f"Temperature: {dg.signatures['temperature']['why']} (opening temperature "
            f"{dg.signatures['temperature']['opening_temp_c']:.1f} °C, coldest "
            f"{dg.signatures['temperature'].get('coldest_temp_c', float('nan')):.1f} °C, range {dg.signatures['temperature']['range_k']:.1f} K, "
            f"constant-ambient misfit {dg.signatures['temperature']['rms_k']:.2f} K)."), ""]
          if dg.signatures.get("temperature", {}).get("why") else []),
        *(_capacity_lines(dg.signatures["capacity"]) if "capacity_scale" in dg.signatures.get("capacity", {}) else []),
        *(_branch_lines(dg.signatures["hysteresis"]) if "half_gap_v" in dg.signatures.get("hysteresis", {}) else []),
        *(_direction_lines(dg.signatures["hysteresis"]["direction"])
          if "half_gap_v" in dg.signatures.get("hysteresis", {}).get("direction", {}) else []),
        *(_relaxation_lines(dg.signatures["diffusion"]) if "ratio" in dg.signatures.get("diffusion", {}) else []),
        *(_kinetics_lines(dg.signatures["kinetics"]) if "i0_c" in dg.signatures.get("kinetics", {}) else []),
        "## Base model (MTS-FOM, refitted on the fit part)",
        "",
        "| " + " | ".join(k for k in dg.base["point"]) + " |",
        "|" + "---|" * len(dg.base["point"]),
        "| " + " | ".join(_fmt(v) for v in dg.base["point"].values()) + " |",
        "",
        f"Voltage RMSE: fit part {dg.base['rmse_fit_mv']:.2f} mV, held out {dg.base['rmse_heldout_mv']:.2f} mV.",
        "",
        "## Where the residual concentrates",
        "",
        "Concentration = share of squared residual / share of samples (flagged ≥ 1.5, ≥ 2 % of samples).",
        "",
        "| kind | region | samples | RMS mV | mean mV | concentration |",
        "|---|---|---|---|---|---|",
    ]
    for g in dg.located[:15]:
        lines.append(f"| {g['kind']} | {g['label']} | {g['n']} | {g['rms_mv']:.2f} | {g['mean_mv']:.2f} | "
                     f"{g['concentration']:.2f} |")
    if not dg.located:
        lines.append("| – | nothing concentrates | | | | |")
    lines += ["", "Residual power by frequency band: " + ", ".join(
        f"{b['label']}: {100 * b['power_share']:.0f} %" for b in dg.located_full["frequency"]), ""]
    lines += [
        "## Candidate physics, best first",
        "",
        ("| effect | significant | held-out gain | RMSE before → after, mV | fit part after, mV | ΔBIC | detection "
        "| lag-1 autocorr before → after |"),
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in dg.effects:
        lines.append(
            f"| {e.name} | {'**yes**' if e.significant else 'no'} | {100 * e.score:.1f} % | "
            f"{e.rmse_before_mv:.2f} → {e.rmse_after_mv:.2f} | {dg.base['rmse_fit_mv']:.2f} → "
            f"{e.rmse_fit_after_mv:.2f} | {e.delta_bic:.1f} | {e.detection:.3f} | "
            f"{e.whiteness_before:.3f} → {e.whiteness_after:.3f} |")
    lines += ["", "### Fitted parameters of each added term (± 1 s.e., inflated for residual autocorrelation)", ""]
    for e in dg.effects:
        ps = ", ".join(
            f"{k} = {_fmt(v)}" + (f" ± {_fmt(e.params_std[k])}" if k in e.params_std else "")
            for k, v in e.params.items())
        why = "" if e.significant else f" — not significant: {'; '.join(e.reasons)}"
        where = "" if e.split == dg.protocol["split"] else f" (fitted and scored on the {e.split} split)"
        lines.append(f"- **{e.name}** ({e.title}){where}: {ps}{why}")
    lines += ["", "## Plots", ""] + [f"![{f}]({f})" for f in files] + [
        "", (f"_{dg.seconds:.0f} s. Detection statistics are |correlation| of the base residual with the effect's "
        "feature (ocv: share of residual variance explained by SOC); they point, the refit decides._"), ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
