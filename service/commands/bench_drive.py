"""The drive current the benchmarks run (``socd bench``, ``--latency``, ``--simulate``): inputs
that do not depend on files."""

from __future__ import annotations

import numpy as np


def pulse_current(rng: np.random.Generator, samples: int, hold: int = 10) -> np.ndarray:
    """Current [A] held at a level drawn every ``hold`` samples (mean 0.5 A, σ 1.5 A)."""
    return np.repeat(rng.normal(0.5, 1.5, samples // hold + 1), hold)[:samples]
