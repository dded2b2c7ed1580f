"""The drive the benchmarks run (``socd bench``, ``--latency``, ``--simulate``): inputs that do
not depend on files."""

from __future__ import annotations

import numpy as np


def pulse_current(rng: np.random.Generator, samples: int, hold: int = 10) -> np.ndarray:
    """Current [A] held at a level drawn every ``hold`` samples (mean 0.5 A, σ 1.5 A)."""
    return np.repeat(rng.normal(0.5, 1.5, samples // hold + 1), hold)[:samples]


def pack_drive(profile, n_cells: int, samples: int, dt_s: float, hold: int,
               seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Pack current (:func:`pulse_current`) and per-cell terminal voltages simulated with the
    cell model at 25 °C from a spread of start SOC (0.6-0.9), with 2 mV noise."""
    from service.cell.model import MtsFom

    rng = np.random.default_rng(seed)
    current = pulse_current(rng, samples, hold)
    temp = np.full(n_cells, 25.0)
    model = MtsFom(profile, profile.parameters_at(temp), rng.uniform(0.6, 0.9, n_cells))
    volts = np.empty((samples, n_cells))
    for k in range(samples):
        volts[k] = model.step(dt_s, np.full(n_cells, current[k]), temp) + rng.normal(0, 0.002, n_cells)
    return current, volts
