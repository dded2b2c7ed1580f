"""Shared fixtures for the cell-model and estimator tests.

A small synthetic NMC-like cell (2.0 Ah, R_ohm 20 mΩ, R_ct 10 mΩ with τ 10 s, R_df
20 mΩ with τ 300 s, orders 0.8 / 0.7), a seeded pulse/rest current profile, and a
helper that simulates a recording with :func:`service.cell.trajectory.simulate`, adds
voltage noise and writes the CSV a ``socd`` command reads.

Every fixture is named for what it is (``nmc_*``) and none is autouse, so the test
files that do not use them are unaffected.  Simulations are cached per argument set
(they are the slow part); the CSV is written to each test's own ``tmp_path``.
"""

from __future__ import annotations

import csv
import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

# CI runs the property-based tests on a fixed seed sequence, so a submission's result does not
# depend on which examples the draw found; a developer's run explores new ones each time
settings.register_profile("ci", derandomize=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

from service.cell.profile import CellProfile, Extensions, HysteresisSpec, OcvSpec, ParameterPoint
from service.cell.trajectory import simulate

NMC_CAPACITY_AH = 2.0
TAU_CT_S = 10.0
TAU_DF_S = 300.0
#: the true parameters of the synthetic cell; C from τ^α = R·C of a CPE branch
NMC_PARAMETERS: dict[str, float] = {
    "r_ohm": 0.02,
    "r_ct": 0.01,
    "c_dl": TAU_CT_S**0.8 / 0.01,
    "m": 0.8,
    "r_df": 0.02,
    "c_df": TAU_DF_S**0.7 / 0.02,
    "n": 0.7,
}


def nmc_ocv_points() -> tuple[np.ndarray, np.ndarray]:
    """OCV(SOC) shaped like an NMC cell: steep knee near empty, 3.4 V to 4.2 V."""
    soc = np.linspace(0.0, 1.0, 41)
    ocv = (
        3.40
        + 0.78 * soc
        - 0.25 * np.exp(-soc / 0.06)
        - 0.05 * np.exp(-(((soc - 0.55) / 0.12) ** 2))
        + 0.05 * soc**4
    )
    return soc, ocv


def make_nmc_profile(
    temps_c: tuple[float, ...] = (25.0,),
    hysteresis: HysteresisSpec | None = None,
    extensions: Extensions | None = None,
    **parameters: float,
) -> CellProfile:
    """The synthetic cell; keyword arguments override :data:`NMC_PARAMETERS`."""
    soc, ocv = nmc_ocv_points()
    point = {**NMC_PARAMETERS, **parameters}
    return CellProfile(
        name="nmc-test",
        capacity_ah=NMC_CAPACITY_AH,
        ocv=OcvSpec(soc=soc.tolist(), temps_c=list(temps_c), ocv_v=[ocv.tolist() for _ in temps_c]),
        parameters=[ParameterPoint(temp_c=t, **point) for t in temps_c],
        hysteresis=hysteresis or HysteresisSpec(),
        extensions=extensions or Extensions(),
    )


def pulse_current(
    n_samples: int, capacity_ah: float = NMC_CAPACITY_AH, seed: int = 0, rest_first_s: int = 60
) -> np.ndarray:
    """Seeded pulses and rests at 1 sample per step: levels from 2C discharge to 1C
    charge held 10-200 samples, net discharge; the first ``rest_first_s`` samples rest."""
    rng = np.random.default_rng(seed)
    levels = np.array([2.0, 1.0, 0.5, 0.0, 0.0, -0.5, -1.0])
    out: list[float] = []
    while len(out) < n_samples:
        out += [float(rng.choice(levels)) * capacity_ah] * int(rng.integers(10, 200))
    cur = np.array(out[:n_samples])
    cur[:rest_first_s] = 0.0
    return cur


@dataclass(frozen=True)
class SimulatedRecording:
    """A simulated recording: the arrays and the CSV written from them."""

    path: Path
    time_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray  # with noise, as written
    voltage_clean_v: np.ndarray
    temperature_c: np.ndarray
    soc_true: np.ndarray

    def __len__(self) -> int:
        return int(self.time_s.size)


def write_recording_csv(
    path: Path,
    time_s: np.ndarray,
    current_a: np.ndarray,
    voltage_v: np.ndarray,
    temperature_c: np.ndarray,
    soc_true: np.ndarray | None = None,
) -> Path:
    """Write the shared recording CSV format (``time_s,current_a,voltage_v,temperature_c[,soc_true]``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ["time_s", "current_a", "voltage_v", "temperature_c"] + ([] if soc_true is None else ["soc_true"])
    cols = [time_s, current_a, voltage_v, temperature_c] + ([] if soc_true is None else [soc_true])
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row in zip(*cols):
            w.writerow([repr(float(x)) for x in row])
    return path


@functools.lru_cache(maxsize=32)
def _simulate_cached(
    duration_s: int, seed: int, soc0: float, noise_v: float, dt_s: float, temp_c: float, profile_key: tuple
) -> tuple[np.ndarray, ...]:
    profile = make_nmc_profile(**dict(profile_key))
    n = round(duration_s / dt_s)
    t = np.arange(n, dtype=float) * dt_s
    i = pulse_current(n, NMC_CAPACITY_AH, seed)
    temp = np.full(n, float(temp_c))
    v, soc = simulate(profile, t, i, temp, soc0)
    noise = np.random.default_rng(seed + 1000).normal(0.0, noise_v, n) if noise_v > 0 else np.zeros(n)
    for a in (t, i, temp, v, soc, noise):
        a.flags.writeable = False
    return t, i, temp, v, soc, noise


def simulate_recording(
    directory: Path,
    name: str = "sim",
    duration_s: int = 7200,
    seed: int = 0,
    soc0: float = 0.9,
    noise_v: float = 0.002,
    dt_s: float = 1.0,
    temp_c: float = 25.0,
    with_truth: bool = True,
    **parameters: float,
) -> SimulatedRecording:
    """Simulate the synthetic cell (parameters overridable) under :func:`pulse_current`,
    add Gaussian voltage noise σ ``noise_v`` and write ``directory/name.csv``."""
    key = tuple(sorted(parameters.items()))
    t, i, temp, v, soc, noise = _simulate_cached(duration_s, seed, soc0, noise_v, dt_s, temp_c, key)
    t, i, temp, v, soc = (np.array(a) for a in (t, i, temp, v, soc))
    v_noisy = v + noise
    path = write_recording_csv(directory / f"{name}.csv", t, i, v_noisy, temp, soc if with_truth else None)
    return SimulatedRecording(path, t, i, v_noisy, v, temp, soc)


@pytest.fixture
def nmc_profile() -> CellProfile:
    """The synthetic NMC-like cell with its true parameters."""
    return make_nmc_profile()


@pytest.fixture
def nmc_true_parameters() -> dict[str, float]:
    """The synthetic cell's true parameters (:data:`NMC_PARAMETERS`), a copy."""
    return dict(NMC_PARAMETERS)


@pytest.fixture
def nmc_profile_factory() -> Callable[..., CellProfile]:
    """:func:`make_nmc_profile`: the synthetic cell with parameters overridden."""
    return make_nmc_profile


@pytest.fixture
def nmc_current() -> Callable[..., np.ndarray]:
    """:func:`pulse_current`: seeded pulse/rest current, positive = discharge."""
    return pulse_current


@pytest.fixture
def nmc_recording(tmp_path: Path) -> Callable[..., SimulatedRecording]:
    """Factory: :func:`simulate_recording` into this test's ``tmp_path``."""
    return functools.partial(simulate_recording, tmp_path)


@pytest.fixture
def nmc_ocv_csv(tmp_path: Path) -> Path:
    """The synthetic cell's OCV table as a ``soc,ocv_v`` CSV (what ``socd fit --ocv`` reads)."""
    soc, ocv = nmc_ocv_points()
    path = tmp_path / "nmc_ocv.csv"
    path.write_text("soc,ocv_v\n" + "".join(f"{float(s)!r},{float(v)!r}\n" for s, v in zip(soc, ocv)))
    return path


@pytest.fixture
def nmc_profile_file(tmp_path: Path, nmc_profile: CellProfile) -> Path:
    """The synthetic cell saved as a TOML profile."""
    from service.cell.profile import save_profile

    path = tmp_path / "nmc.toml"
    save_profile(nmc_profile, path)
    return path
