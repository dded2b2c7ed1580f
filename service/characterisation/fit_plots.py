"""PNG plots of a fitted profile against the recordings it was fitted on (``socd fit --plots DIR``).

For each dynamic recording, cut at its full-charge point as the fit cut it: the measured voltage,
the fractional model and the textbook 2-RC model simulated along it with the parameters following
the recorded temperature (:func:`service.cell.trajectory.simulate`; the 2-RC model in the
fractional form, :func:`service.characterisation.two_rc_profile.with_two_rc_points`), their
residuals with each one's RMSE, and the current and temperature.  One more plot shows the
profile's OCV(SOC) at each of its temperatures.  An engineer sees at once where a model misses:
near empty, in the cold bursts, or in the rests.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.cell.profile import CellProfile
from service.cell.trajectory import simulate
from service.cell.truth import truth_and_start
from service.cell.units import SECONDS_PER_HOUR
from service.characterisation.ocv_sources import is_ocv_test
from service.characterisation.two_rc_profile import with_two_rc_points
from service.recording import Recording


@dataclass(frozen=True)
class FitPlot:
    """One recording's plot and the two models' voltage RMSE [mV] along it."""

    path: Path
    recording: str
    fractional_rmse_mv: float
    two_rc_rmse_mv: float | None


def plot_fit(profile: CellProfile, recordings: list[Recording], full_at: list[str | float | None],
             out_dir: Path) -> list[FitPlot]:
    """Write ``<recording>_fit.png`` for every dynamic recording and ``ocv.png``; return the plots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    two_rc = with_two_rc_points(profile) if profile.ecm2rc is not None else None
    plots = []
    for rec, fa in zip(recordings, full_at):
        if is_ocv_test(rec, profile.capacity_ah):
            continue
        part, soc = truth_and_start(rec, profile.capacity_ah, fa)
        models = {"fractional": profile} | ({"textbook 2-RC": two_rc} if two_rc is not None else {})
        rmse = {}
        t_h = (part.time_s - part.time_s[0]) / SECONDS_PER_HOUR
        fig, axes = plt.subplots(3, 1, figsize=(11, 9), sharex=True, height_ratios=(3, 2, 1.5))
        axes[0].plot(t_h, part.voltage_v, "k", lw=0.8, label="measured")
        for label, prof in models.items():
            v, _ = simulate(prof, part.time_s, part.current_a, part.temperature_c, float(soc[0]))
            err = 1000.0 * (v - part.voltage_v)
            rmse[label] = float(np.sqrt(np.mean(err[np.isfinite(err)] ** 2)))
            axes[0].plot(t_h, v, lw=0.7, label=label)
            axes[1].plot(t_h, err, lw=0.6, label=f"{label}: RMSE {rmse[label]:.1f} mV")
        axes[0].set_ylabel("voltage [V]")
        axes[0].legend(fontsize=8, ncol=3)
        axes[1].axhline(0.0, color="grey", lw=0.5)
        axes[1].set_ylabel("model − measured [mV]")
        axes[1].legend(fontsize=8)
        axes[2].plot(t_h, part.current_a, lw=0.6, color="tab:grey")
        axes[2].set_ylabel("current [A]\n(+ discharge)")
        temp_ax = axes[2].twinx()
        temp_ax.plot(t_h, part.temperature_c, lw=0.8, color="tab:red")
        temp_ax.set_ylabel("°C", color="tab:red")
        axes[2].set_xlabel("time from the full-charge point [h]")
        fig.suptitle(f"{rec.name}: the fitted models along the recording")
        fig.tight_layout()
        path = out_dir / f"{_safe(rec.name)}_fit.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        plots.append(FitPlot(path, rec.name, rmse["fractional"], rmse.get("textbook 2-RC")))
    plot_ocv(profile, out_dir / "ocv.png")
    return plots


def plot_ocv(profile: CellProfile, path: Path) -> Path:
    """The profile's OCV(SOC) at each temperature it holds (and the 2-RC model's, where it differs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = profile.ocv_table()
    soc = np.linspace(0.0, 1.0, 201)
    fig, ax = plt.subplots(figsize=(8, 5))
    for temp in table.temps_c:
        ax.plot(100 * soc, table.ocv(soc, np.full(soc.size, temp)), lw=1, label=f"{temp:g} °C")
    if profile.ecm2rc is not None:
        ecm = profile.ecm2rc.ocv_table()
        for temp in ecm.temps_c:
            v = ecm.ocv(soc, np.full(soc.size, temp))
            if np.max(np.abs(v - table.ocv(soc, np.full(soc.size, temp)))) > 1e-3:
                ax.plot(100 * soc, v, lw=0.8, ls="--", label=f"{temp:g} °C (2-RC model)")
    ax.set_xlabel("SOC [%]")
    ax.set_ylabel("OCV [V]")
    ax.set_title(f"{profile.name}: OCV(SOC, T)")
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)
