"""Online capacity and resistance growth per cell (service.estimators.capacity, issue 28).

- frozen (``capacity_estimation = 'off'``) builds no estimator, and a one-cell pack in the
  default mode runs exactly as frozen (single-cell evaluation is unchanged);
- on a demo-like pack (the bundled drive's first 40 minutes, 5 % capacity spread) the learned
  capacities track the cells' spread and the SOC error of the worst cell falls against the frozen run;
- the pack-relative mode weighs its measurement by the innovation variance without the SOC
  filter's model-error terms (that error is common to the pack and cancels), the absolute mode
  by the whole innovation variance;
- the state survives a round trip, and a state written without it still restores;
- SOCD_CellHealth and the schema-2 CellParams carry it.
"""

from __future__ import annotations

import numpy as np
import pytest

from replay.pack import SpreadSpec, expand_pack
from service.assets import bundled_recording
from service.bus.encoder import OutputEncoder, decode_output
from service.bus.types import PackSnapshot
from service.cell.profile import load_profile
from service.config import DEFAULT_CELL_PROFILE
from service.daemon.payloads import PARAMS_SCHEMA_VERSION, CellParams
from service.estimators.capacity import CapacityEstimator
from service.estimators.pipeline import PackEstimator
from service.estimators.settings import EstimatorSettings
from service.estimators.state_of_health import CellHealth
from service.recording import load_recording


def _pack(n: int, seconds: float, spread: float = 0.05, seed: int = 0):
    profile = load_profile(DEFAULT_CELL_PROFILE)
    rec = load_recording(bundled_recording())
    rec = rec.slice(0, int(np.searchsorted(rec.time_s, rec.time_s[0] + seconds)))
    pack = expand_pack(rec, profile, n, SpreadSpec(capacity=spread, resistance=0.05, soc=0.02), seed=seed,
                       start_soc=1.0)
    return profile, pack


def _run(profile, pack, mode: str) -> tuple[PackEstimator, np.ndarray]:
    est = PackEstimator(profile, pack.n_cells, EstimatorSettings(capacity_estimation=mode))
    est.initialise(pack.voltage_v[0], pack.temperature_c[0], pack.current_a[0])
    soc = np.empty_like(pack.truth_soc)
    soc[0] = est.soc
    for k in range(1, len(pack)):
        est.step(pack.time_s[k] - pack.time_s[k - 1], pack.current_a[k], pack.voltage_v[k], pack.temperature_c[k])
        if k % 10 == 0:
            est.slow_update()
        soc[k] = est.soc
    return est, soc


def test_frozen_has_no_estimator_and_one_cell_runs_as_frozen() -> None:
    profile, pack = _pack(1, 300)
    frozen, soc_frozen = _run(profile, pack, "off")
    default, soc_default = _run(profile, pack, "pack-relative")
    assert frozen.capacity is None and default.capacity is None
    assert np.array_equal(soc_frozen, soc_default)
    h = frozen.health()
    assert np.all(h.capacity_ah == profile.effective_capacity_ah) and np.all(h.capacity_std_ah == 0)
    assert np.all(np.isfinite(h.resistance_rel)) and np.all(h.resistance_rel > 0)


@pytest.fixture(scope="module")
def learned_and_frozen():
    profile, pack = _pack(8, 2400)  # the drive's first 40 minutes: 100 % to about 55 % SOC
    return pack, _run(profile, pack, "pack-relative"), _run(profile, pack, "off")


def test_capacity_tracks_the_spread_and_lowers_the_worst_soc_error(learned_and_frozen) -> None:
    pack, (est, soc), (_, soc_frozen) = learned_and_frozen
    err = (est.health().capacity_ah / pack.capacity_ah - 1.0) * 100
    frozen_err = (est.profile.effective_capacity_ah / pack.capacity_ah - 1.0) * 100
    # relative to the pack's median cell (what pack-relative learns) every cell is close ...
    spread_left = np.abs(err - np.median(err))
    frozen_left = np.abs(frozen_err - np.median(frozen_err))
    assert spread_left.max() < 2.5 and spread_left.max() < 0.5 * frozen_left.max()
    assert np.sqrt(np.mean(spread_left ** 2)) < 0.5 * np.sqrt(np.mean(frozen_left ** 2))
    # ... the variance learned against the median has shrunk from the prior, while the σ published
    # keeps the pack's common level, which this mode does not observe, and so covers each cell's error
    prior = est.settings.capacity_init_std_rel
    assert np.all(np.sqrt(est.capacity.state.var) < 0.5 * prior)
    std_pct = est.health().capacity_std_ah / est.health().capacity_ah * 100
    assert np.all(std_pct > 100 * prior * 0.9) and np.all(np.abs(err) < 2 * std_pct)
    rel = est.health().capacity_rel
    assert np.all((rel > 1 / 1.3) & (rel < 1 / 0.7))
    rmse = np.sqrt(np.mean((soc - pack.truth_soc) ** 2, axis=0)) * 100
    rmse_frozen = np.sqrt(np.mean((soc_frozen - pack.truth_soc) ** 2, axis=0)) * 100
    assert rmse.max() < rmse_frozen.max()


def test_no_update_from_a_poorly_observed_or_stale_cell() -> None:
    cap = CapacityEstimator(3, 3.0, "absolute", 0.05, 0.3, 10.0, 0.0)
    usable = np.array([True, False, False])
    for _ in range(200):
        shift = cap.update(np.full(3, 3.0), 1.0, np.full(3, 0.02), np.full(3, 1e-4), np.full(3, 0.8),
                           np.zeros(3), usable)
        assert np.all(shift[~usable] == 0.0)
    phi = cap.state.phi
    assert phi[0] != 1.0 and np.all(phi[1:] == 1.0)
    assert cap.bounds[0] <= phi[0] <= cap.bounds[1]


def _learned_phi(mode: str, innovation_var: float, innovation_var_own: float | None) -> np.ndarray:
    """φ after a few samples of a discharge in which cell 0 reads 5 mV above the others."""
    cap = CapacityEstimator(3, 3.0, mode, 0.05, 0.3, 10.0, 0.0)
    innovation = np.array([0.005, 0.0, 0.0])
    own = None if innovation_var_own is None else np.full(3, innovation_var_own)
    for _ in range(50):
        cap.update(np.full(3, 3.0), 1.0, innovation, np.full(3, innovation_var), np.full(3, 0.8),
                   np.zeros(3), np.ones(3, dtype=bool), own)
    return cap.state.phi


def test_pack_relative_measurement_noise_leaves_out_the_common_model_error() -> None:
    small, large = 1e-5, 1e-2  # V²: state spread and sensor; with a large model-error term
    relative = _learned_phi("pack-relative", large, small)
    assert np.array_equal(relative, _learned_phi("pack-relative", small, None))
    assert abs(relative[0] - 1.0) > 10 * abs(_learned_phi("pack-relative", large, None)[0] - 1.0)
    absolute = _learned_phi("absolute", large, small)
    assert np.array_equal(absolute, _learned_phi("absolute", large, None))


def test_state_round_trip_and_old_state_without_capacity(learned_and_frozen) -> None:
    _, (est, _), _ = learned_and_frozen
    state = est.get_state()
    restored = PackEstimator(est.profile, est.n, est.settings)
    restored.set_state(state)
    assert np.array_equal(restored.health().capacity_ah, est.health().capacity_ah)
    old = {k: v for k, v in state.items() if k not in CapacityEstimator.STATE_KEYS}
    legacy = PackEstimator(est.profile, est.n, est.settings)
    legacy.set_state(old)
    assert np.all(legacy.health().capacity_ah == est.profile.effective_capacity_ah)
    assert np.array_equal(legacy.soc, est.soc)


def test_cell_health_frame_and_params_payload() -> None:
    n = 3
    health = CellHealth(capacity_ah=np.array([2.7, 2.9, 3.1]), capacity_std_ah=np.array([0.03, 0.02, 0.01]),
                        capacity_rel=np.array([2.7, 2.9, 3.1]) / 2.8, resistance_rel=np.array([1.0, 1.25, 0.9]))
    snap = PackSnapshot(t_s=1.0, soc=np.full(n, 0.5), soc_std=np.full(n, 0.01), voltage_v=np.full(n, 3.7),
                        health=health)
    enc = OutputEncoder()
    frames = enc.encode(snap)
    got = [decode_output(f) for f in frames]
    rows = [g for g in got if g.get("message") == "SOCD_CellHealth"]
    assert len(rows) == n and frames[-1].arbitration_id == 0x18FF55E5 and frames[-1].is_extended_id
    for i, g in enumerate(rows):
        assert g["SOCD_HlthCellIndex"] == i
        assert g["SOCD_CapacityPct"] == pytest.approx(100 * health.capacity_rel[i], abs=0.01)
        assert g["SOCD_CapacityStdPct"] == pytest.approx(100 * health.capacity_std_ah[i] / 2.8, abs=0.01)
        assert g["SOCD_ResistancePct"] == pytest.approx(100 * health.resistance_rel[i], abs=0.1)
    # a snapshot without health sends no health frames (older callers, frozen tools)
    assert not any(decode_output(f).get("message") == "SOCD_CellHealth"
                   for f in enc.encode(PackSnapshot(t_s=1.0, soc=np.full(n, 0.5), soc_std=np.full(n, 0.01),
                                                    voltage_v=np.full(n, 3.7))))
    p = CellParams(pack="p", t_s=0.0, cell=0, capacity_ah=2.9, capacity_std_ah=0.02, capacity_pct=103.6,
                   resistance_pct=125.0)
    assert p.schema_version == PARAMS_SCHEMA_VERSION == 2
    assert CellParams.model_validate_json(p.model_dump_json()) == p
