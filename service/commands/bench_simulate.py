"""``socd bench --simulate``: samples per second of the offline model simulation that
``socd fit`` and ``socd diagnose`` run (:mod:`service.cell.trajectory`), against stepping the
same model one sample at a time (:func:`service.cell.model.drive`) on the same inputs."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from service.cell.profile import CellProfile
from service.commands.bench_drive import pulse_current

#: the drive's time step and its jitter (real loggers stamp 1 s samples a few ms apart)
STEP_S = 1.0
JITTER_S = 0.002


@dataclass(frozen=True)
class SimulateBench:
    candidates: int
    steps: int
    reference_steps: int
    samples_per_s: float  # candidate-samples per second, array-wise along the recording
    reference_samples_per_s: float  # the same, stepping MtsFom one sample at a time
    ratio: float
    max_abs_diff_v: float  # largest voltage difference of the two over the reference steps

    def to_json(self) -> dict:
        return asdict(self)

    def text(self) -> str:
        return "\n".join([
            f"model simulation, {self.candidates} parameter candidates along jittered {STEP_S:g} s samples, "
            "one core",
            f"  along the recording (trajectory): {self.samples_per_s:14,.0f} candidate-samples/s "
            f"({self.steps} samples)",
            f"  stepping MtsFom (reference)     : {self.reference_samples_per_s:14,.0f} candidate-samples/s "
            f"({self.reference_steps} samples)",
            f"  ratio                           : {self.ratio:14.1f} x",
            f"  largest voltage difference      : {self.max_abs_diff_v:14.1e} V",
        ])


def _drive(steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time, current and temperature of a pulse drive with jittered sample times."""
    rng = np.random.default_rng(seed)
    current = pulse_current(rng, steps)
    time_s = np.concatenate([[0.0], np.cumsum(STEP_S + rng.uniform(-JITTER_S, JITTER_S, steps - 1))])
    return time_s, current, np.full(steps, 25.0)


def _candidates(profile: CellProfile, n: int, seed: int):
    """``n`` parameter sets around the profile's at 25 °C (resistances and orders spread)."""
    rng = np.random.default_rng(seed)
    params = profile.parameters_at(25.0, n_cells=n)
    params.r[...] *= rng.uniform(0.5, 2.0, params.r.shape)
    params.alpha[...] = np.clip(params.alpha * rng.uniform(0.8, 1.0, params.alpha.shape), 0.3, 1.0)
    return params


def run_simulate_bench(profile: CellProfile, candidates: int, steps: int, reference_steps: int,
                       seed: int = 0) -> SimulateBench:
    from service.cell.model import MtsFom, drive
    from service.cell.trajectory import simulate_batch

    time_s, current, temp = _drive(max(steps, reference_steps), seed)
    params = _candidates(profile, candidates, seed)
    soc0 = np.full(candidates, 0.9)
    simulate_batch(profile, time_s[:50], current[:50], temp[:50], soc0, params)  # warm-up
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        simulate_batch(profile, time_s[:steps], current[:steps], temp[:steps], soc0, params)
        best = min(best, time.perf_counter() - t0)
    t0 = time.perf_counter()
    v_ref, _ = drive(MtsFom(profile, params, soc0), time_s[:reference_steps], current[:reference_steps],
                     temp[:reference_steps], follow_temperature=False)
    ref_s = time.perf_counter() - t0
    v, _ = simulate_batch(profile, time_s[:reference_steps], current[:reference_steps],
                          temp[:reference_steps], soc0, params)
    rate = candidates * steps / best
    ref_rate = candidates * reference_steps / ref_s
    return SimulateBench(candidates=candidates, steps=steps, reference_steps=reference_steps,
                         samples_per_s=rate, reference_samples_per_s=ref_rate, ratio=rate / ref_rate,
                         max_abs_diff_v=float(np.max(np.abs(v - v_ref))))
