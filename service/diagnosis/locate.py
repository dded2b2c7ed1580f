"""Where the residual concentrates: time windows and operating regions.

Every region is reported with its sample share, its residual RMS and mean, and its
*concentration*: the share of the total squared residual it holds divided by its share
of the samples (1 = average; 2 = twice its fair share).  A region is flagged when its
concentration is at least :data:`CONCENTRATION_FLAG` and it holds at least 2 % of the
samples.
"""

from __future__ import annotations

import numpy as np

CONCENTRATION_FLAG = 1.5
MIN_SHARE = 0.02


def _region(kind: str, label: str, mask: np.ndarray, r: np.ndarray, total_ss: float) -> dict | None:
    n = int(mask.sum())
    if n == 0:
        return None
    share = n / r.size
    ss = float(np.sum(r[mask] ** 2))
    conc = (ss / total_ss) / share if total_ss > 0 else 0.0
    return {
        "kind": kind,
        "label": label,
        "n": n,
        "share": round(share, 4),
        "rms_mv": round(1000 * float(np.sqrt(ss / n)), 3),
        "mean_mv": round(1000 * float(np.mean(r[mask])), 3),
        "concentration": round(conc, 3),
        "flagged": bool(conc >= CONCENTRATION_FLAG and share >= MIN_SHARE),
    }


def time_since_change(time_s: np.ndarray, current_a: np.ndarray, step_a: float) -> np.ndarray:
    """Seconds since the last current change larger than ``step_a``."""
    out = np.empty_like(time_s)
    last = time_s[0]
    di = np.abs(np.diff(current_a, prepend=current_a[0]))
    for k in range(time_s.size):
        if di[k] > step_a:
            last = time_s[k - 1] if k else time_s[0]
        out[k] = time_s[k] - last
    return out


def time_windows(time_s: np.ndarray, r: np.ndarray, n_windows: int = 20) -> list[dict]:
    """Equal-duration windows with their residual statistics (flagged ones concentrate)."""
    edges = np.linspace(time_s[0], time_s[-1], n_windows + 1)
    total = float(np.sum(r**2))
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (time_s >= a) & (time_s <= b)
        reg = _region("time", f"{a:.0f}-{b:.0f} s", m, r, total)
        if reg:
            reg["t_start_s"], reg["t_end_s"] = float(a), float(b)
            out.append(reg)
    return out


def band_power(time_s: np.ndarray, r: np.ndarray) -> list[dict]:
    """Residual power per frequency band (on the median sample period)."""
    dt = float(np.median(np.diff(time_s)))
    x = r - r.mean()
    spec = np.abs(np.fft.rfft(x)) ** 2
    f = np.fft.rfftfreq(x.size, dt)
    total = float(spec[1:].sum()) or 1.0
    bands = [(0.0, 1e-3, "< 1 mHz (> 17 min)"), (1e-3, 1e-2, "1-10 mHz (100 s - 17 min)"),
             (1e-2, 1e-1, "10-100 mHz (10-100 s)"), (1e-1, np.inf, "> 100 mHz (< 10 s)")]
    out = []
    for lo, hi, label in bands:
        m = (f > lo) & (f <= hi)
        m[0] = False
        if m.any():
            out.append({"kind": "frequency", "label": label, "power_share": round(float(spec[m].sum()) / total, 4)})
    return out


def locate(time_s, current_a, temperature_c, soc, r, capacity_ah: float) -> dict:
    """All located regions: ``{"windows": [...], "regions": [...], "frequency": [...]}``."""
    total = float(np.sum(r**2))
    c_rate = np.abs(current_a) / capacity_ah
    rest = c_rate < 0.01
    regions = []

    def add(kind, label, mask):
        reg = _region(kind, label, mask, r, total)
        if reg:
            regions.append(reg)

    edges = np.arange(0.0, 1.0001, 0.1)
    for a, b in zip(edges[:-1], edges[1:]):
        add("soc", f"SOC {a:.1f}-{b:.1f}", (soc >= a) & (soc < b + (1e-9 if b >= 1 else 0)))
    add("soc", "SOC < 0", soc < 0)
    add("soc", "SOC > 1", soc > 1 + 1e-9)
    t_lo, t_hi = np.floor(temperature_c.min()), np.ceil(temperature_c.max())
    if t_hi - t_lo >= 2:
        for a, b in zip(*(lambda e: (e[:-1], e[1:]))(np.linspace(t_lo, t_hi, 5))):
            add("temperature", f"{a:.1f}-{b:.1f} C", (temperature_c >= a) & (temperature_c <= b))
    add("direction", "discharge", (~rest) & (current_a > 0))
    add("direction", "charge", (~rest) & (current_a < 0))
    add("direction", "rest", rest)
    for a, b in ((0.01, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, np.inf)):
        add("c_rate", f"{a:g}-{b:g} C" if np.isfinite(b) else f"> {a:g} C", (c_rate >= a) & (c_rate < b))
    since = time_since_change(time_s, current_a, 0.1 * capacity_ah)
    for a, b in ((0, 10), (10, 60), (60, 600), (600, np.inf)):
        lab = f"{a}-{b} s after a step" if np.isfinite(b) else f"> {a} s after a step"
        add("relaxation", lab + " (rest)", rest & (since >= a) & (since < b))
        add("relaxation", lab + " (load)", (~rest) & (since >= a) & (since < b))
    return {"windows": time_windows(time_s, r), "regions": regions, "frequency": band_power(time_s, r)}
