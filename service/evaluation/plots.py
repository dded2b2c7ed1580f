"""PNG plots of an evaluation: SOC vs truth, SOC error with each estimator's published ±2σ, voltage
residual, parameters."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.cell.units import SECONDS_PER_HOUR
from service.estimators.base import EstimateTrace


def plot_recording(path: Path, name: str, time_s: np.ndarray, truth: np.ndarray, v_meas: np.ndarray,
                   traces: dict[str, EstimateTrace]) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.mkdir(parents=True, exist_ok=True)
    t_h = (time_s - time_s[0]) / SECONDS_PER_HOUR
    out: list[Path] = []
    fig, axes = plt.subplots(3, 1, figsize=(11, 10), sharex=True)
    axes[0].plot(t_h, 100 * truth, "k", lw=2, label="truth")
    for est, tr in traces.items():
        axes[0].plot(t_h, 100 * tr.soc, lw=1, label=est)
        line, = axes[1].plot(t_h, 100 * (tr.soc - truth), lw=1, label=est)
        if tr.soc_std is not None:  # the ±2σ band the estimator publishes, in its colour
            band = 200 * tr.soc_std
            axes[1].fill_between(t_h, -band, band, color=line.get_color(), alpha=0.12, lw=0)
        if tr.v_pred is not None:
            axes[2].plot(t_h, 1000 * (v_meas - tr.v_pred), lw=0.6, label=est)
    axes[0].set_ylabel("SOC [%]")
    axes[0].legend(fontsize=8, ncol=4)
    axes[1].set_ylabel("SOC error [%] (shaded: ±2σ published)")
    axes[1].axhline(2, color="grey", ls=":")
    axes[1].axhline(-2, color="grey", ls=":")
    axes[1].set_ylim(-10, 10)
    axes[2].set_ylabel("V measured − predicted [mV]")
    axes[2].set_xlabel("time [h]")
    fig.suptitle(name)
    fig.tight_layout()
    p = path / f"{name}_soc.png"
    fig.savefig(p, dpi=90)
    plt.close(fig)
    out.append(p)
    for est, tr in traces.items():
        if not tr.params:
            continue
        keys = list(tr.params)
        fig, axes = plt.subplots(len(keys), 1, figsize=(11, 1.6 * len(keys) + 1), sharex=True)
        for ax, key in zip(np.atleast_1d(axes), keys):
            ax.plot(t_h, tr.params[key], lw=0.8)
            ax.set_ylabel(key, fontsize=8)
        np.atleast_1d(axes)[-1].set_xlabel("time [h]")
        fig.suptitle(f"{name}: identified parameters ({est})")
        fig.tight_layout()
        p = path / f"{name}_{est}_params.png"
        fig.savefig(p, dpi=80)
        plt.close(fig)
        out.append(p)
    return out
