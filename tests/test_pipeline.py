"""PackEstimator and the offline pipeline estimators: convergence, batch = single, stale
cells, state round trip, divergence handling."""

from __future__ import annotations

import numpy as np
import pytest

from service.cell.model import MtsFom
from service.estimators.adaptive_noise import N_SHAPE_MOMENTS
from service.estimators.pipeline import PackEstimator, fom_single_scale, fomiukf, foukf
from service.estimators.settings import EstimatorSettings
from service.recording import load_recording

ESTIMATORS = {"fomiukf": fomiukf, "foukf": foukf, "fom-single-scale": fom_single_scale}


def _rmse_after(err: np.ndarray, time_s: np.ndarray, after_s: float = 600.0) -> float:
    return float(np.sqrt(np.mean(err[time_s - time_s[0] >= after_s] ** 2)))


# -- convergence -------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_converges_from_wrong_start(nmc_recording, nmc_profile, name: str) -> None:
    rec = nmc_recording(duration_s=900, seed=0, soc0=0.9)
    trace = ESTIMATORS[name]().run(load_recording(rec.path), nmc_profile, 0.7)
    err = trace.soc - rec.soc_true
    assert _rmse_after(err, rec.time_s) < 0.03
    assert abs(err[-1]) < 0.03
    assert np.all(np.isfinite(trace.soc_std)) and trace.soc_std[-1] < trace.soc_std[0]
    assert np.all(np.isfinite(trace.v_pred))


def test_single_scale_converges_at_mid_soc(nmc_recording, nmc_profile) -> None:
    rec = nmc_recording(duration_s=900, seed=0, soc0=0.5)
    trace = fom_single_scale().run(load_recording(rec.path), nmc_profile, 0.7)
    assert _rmse_after(trace.soc - rec.soc_true, rec.time_s) < 0.03


def test_full_pipeline_parameters_stay_near_truth(nmc_recording, nmc_profile, nmc_true_parameters) -> None:
    rec = nmc_recording(duration_s=900, seed=0, soc0=0.5)
    trace = fomiukf().run(load_recording(rec.path), nmc_profile, 0.7)
    for name in ("r_ohm", "r_ct", "r_df"):
        ratio = trace.params[name][-1] / nmc_true_parameters[name]
        assert 0.5 < ratio < 2.0, (name, ratio)


# -- a pack: batch = single cells -----------------------------------------------------------------
def _pack_data(profile, n_cells: int, steps: int, seed: int):
    """Per-cell currents (different pulse trains and scales), cells differing in R_ohm
    and SOC, voltages simulated by the model with 2 mV noise."""
    rng = np.random.default_rng(seed)
    levels = np.array([4.0, 2.0, 1.0, 0.0, 0.0, -1.0, -2.0])
    current = np.empty((steps, n_cells))
    for c in range(n_cells):
        k = 0
        while k < steps:
            hold = int(rng.integers(5, 60))
            current[k : k + hold, c] = rng.choice(levels) * rng.uniform(0.3, 1.2)
            k += hold
    current[:5] = 0.0
    params = profile.parameters_at(25.0, n_cells=n_cells)
    params.r_ohm = params.r_ohm * rng.uniform(0.8, 1.2, n_cells)
    soc0 = rng.uniform(0.3, 0.95, n_cells)
    model = MtsFom(profile, params, soc0)
    temp = np.full(n_cells, 25.0)
    voltage = np.empty((steps, n_cells))
    soc = np.empty((steps, n_cells))
    for k in range(steps):
        voltage[k] = model.step(1.0 if k else 0.0, current[k], temp)
        soc[k] = model.soc
    voltage += rng.normal(0.0, 0.002, voltage.shape)
    start = np.clip(soc0 + rng.choice([-0.1, 0.1], n_cells), 0.0, 1.0)
    return current, voltage, temp, start, soc


def _batch_vs_single(profile, settings: EstimatorSettings, cells: list[int], n_cells: int = 200, steps: int = 300):
    current, voltage, temp, start, _ = _pack_data(profile, n_cells, steps, seed=5)
    pack = PackEstimator(profile, n_cells, settings)
    pack.start(start)
    for k in range(steps):
        pack.step(1.0 if k else 0.0, current[k], voltage[k], temp)
        pack.slow_update()
    singles = []
    for c in cells:
        one = PackEstimator(profile, 1, settings)
        one.start(start[c : c + 1])
        for k in range(steps):
            one.step(1.0 if k else 0.0, current[k, c : c + 1], voltage[k, c : c + 1], temp[:1])
            one.slow_update()
        singles.append(one)
    return pack, singles


def test_pack_batch_equals_single_cell_runs(nmc_profile) -> None:
    """200 cells with different currents and voltages, estimated together, give the same
    SOC and σ as each cell estimated on its own (checked on a spread of cells: 200 single
    runs would dominate the suite's runtime).  Slow identifier off: see the xfail below."""
    cells = [0, 1, 37, 99, 150, 198, 199]
    pack, singles = _batch_vs_single(nmc_profile, EstimatorSettings(slow_identifier=False, capacity_estimation="absolute"), cells)
    for c, one in zip(cells, singles):
        assert pack.soc[c] == pytest.approx(one.soc[0], rel=1e-9, abs=1e-10), c
        assert pack.soc_std[c] == pytest.approx(one.soc_std[0], rel=1e-7, abs=1e-12), c
        assert pack.v_pred[c] == pytest.approx(one.v_pred[0], abs=1e-9), c
        for name, values in pack.parameters().items():
            assert values[c] == pytest.approx(one.parameters()[name][0], rel=1e-7, abs=1e-12), (c, name)
    assert not pack.reset_count.any()


def test_pack_batch_equals_single_cell_runs_with_slow_identifier(nmc_profile) -> None:
    cells = [1, 199]
    pack, singles = _batch_vs_single(nmc_profile, EstimatorSettings(capacity_estimation="absolute"), cells)
    for c, one in zip(cells, singles):
        assert pack.soc[c] == pytest.approx(one.soc[0], rel=1e-9, abs=1e-10), c


# -- stale cells -----------------------------------------------------------------------------------
def test_stale_cells_take_no_voltage_update_and_their_sigma_grows(nmc_profile) -> None:
    N, warm, stale = 4, 200, 150
    current, voltage, temp, start, _ = _pack_data(nmc_profile, N, warm + stale, seed=2)
    s = EstimatorSettings(capacity_estimation="absolute")  # cells independent: pack-relative couples them
    a, b, ref, all_active = (PackEstimator(nmc_profile, N, s) for _ in range(4))
    for est in (a, b, ref, all_active):
        est.start(start)
    active = np.array([True, False, True, True])
    rng = np.random.default_rng(0)
    stds = []
    for k in range(warm + stale):
        dt = 1.0 if k else 0.0
        if k < warm:
            for est in (a, b, ref, all_active):
                est.step(dt, current[k], voltage[k], temp)
            continue
        all_active.step(dt, current[k], voltage[k], temp)
        garbage = voltage[k].copy()
        garbage[1] = rng.uniform(0.0, 10.0)  # what a stale cell's frame might hold
        nan_v = voltage[k].copy()
        nan_v[1] = np.nan  # a missing value is stale too
        a.step(dt, current[k], voltage[k], temp, active)
        b.step(dt, current[k], garbage, temp, active)
        ref.step(dt, current[k], nan_v, temp)
        stds.append(a.soc_std[1])
    # the stale cell's voltage is not used at all
    for est in (b, ref):
        np.testing.assert_array_equal(est.soc, a.soc)
        np.testing.assert_array_equal(est.soc_std, a.soc_std)
    # its σ grows every step, and the filter's own σ is above what it would be had its voltage kept
    # coming (the σ published also holds the OCV table's error, which a cell reading voltages takes up)
    stds = np.array(stds)
    assert np.all(np.diff(stds) > 0)
    assert a.filter_soc_std[1] > all_active.filter_soc_std[1]
    assert not a.reset_count.any()
    # the other cells are estimated exactly as if cell 1 were not there
    solo = PackEstimator(nmc_profile, 3, s)
    solo.start(start[[0, 2, 3]])
    for k in range(warm + stale):
        solo.step(1.0 if k else 0.0, current[k, [0, 2, 3]], voltage[k, [0, 2, 3]], temp[:3])
    np.testing.assert_allclose(a.soc[[0, 2, 3]], solo.soc, rtol=1e-10, atol=1e-12)


def test_stale_cell_soc_follows_current(nmc_profile) -> None:
    s = EstimatorSettings(innovation_length=1, fast_identifier=False, slow_identifier=False)
    est = PackEstimator(nmc_profile, 2, s)
    est.start(np.array([0.6, 0.6]))
    before = est.soc.copy()
    for _ in range(100):
        est.step(2.0, np.array([1.5, 1.5]), np.array([np.nan, np.nan]), np.full(2, 25.0), np.array([False, False]))
    expected = before - 1.5 * 200.0 / (3600.0 * nmc_profile.capacity_ah)
    np.testing.assert_allclose(est.soc, expected, atol=1e-12)


# -- persistence -----------------------------------------------------------------------------------
def _warm_pack(profile, settings=None, n_cells: int = 3, steps: int = 250, identification="multi"):
    current, voltage, temp, start, _ = _pack_data(profile, n_cells, steps + 5, seed=9)
    est = PackEstimator(profile, n_cells, settings, identification)
    est.start(start)
    for k in range(steps):
        est.step(1.0 if k else 0.0, current[k], voltage[k], temp)
        est.slow_update()
    return est, (current, voltage, temp)


@pytest.mark.parametrize("identification", ["multi", "single", "none"])
def test_state_round_trip_reproduces_next_step(nmc_profile, identification) -> None:
    s = EstimatorSettings()
    est, (current, voltage, temp) = _warm_pack(nmc_profile, s, identification=identification)
    state = est.get_state()
    restored = PackEstimator(nmc_profile, est.n, s, identification)
    restored.set_state(state)
    k = 250
    for e in (est, restored):
        e.step(1.0, current[k], voltage[k], temp)
    np.testing.assert_array_equal(restored.soc, est.soc)
    np.testing.assert_array_equal(restored.soc_std, est.soc_std)
    np.testing.assert_array_equal(restored.v_pred, est.v_pred)
    after_a, after_b = est.get_state(), restored.get_state()
    assert after_a.keys() == after_b.keys()
    for key in after_a:
        np.testing.assert_array_equal(after_a[key], after_b[key], err_msg=key)
    # the state is a copy, not a view on the estimator
    state["ukf_x"][:] = 0.0
    assert np.all(est.ukf.x[:, est.ukf.i_soc] != 0.0)


@pytest.mark.parametrize("shape", ["uniform", "load"])
def test_adaptive_noise_state_round_trips_and_legacy_states_load(nmc_profile, shape) -> None:
    s = EstimatorSettings(adaptive_noise_shape=shape, adaptive_noise_samples=50)
    est, _ = _warm_pack(nmc_profile, s)
    state = est.get_state()
    assert np.any(state["ukf_noise_moments"] != 0.0)
    restored = PackEstimator(nmc_profile, est.n, s, "multi")
    restored.set_state(state)
    np.testing.assert_array_equal(restored.ukf.noise.moments, est.ukf.noise.moments)
    # the fast identifier matches its own innovations the same way
    assert np.any(state["fast_noise_moments"] != 0.0)
    np.testing.assert_array_equal(restored.fast.noise.moments, est.fast.noise.moments)
    older = {k: v for k, v in state.items() if k != "fast_noise_moments"}  # written before it existed
    restored.set_state(older)
    np.testing.assert_array_equal(restored.fast.noise.moments, np.zeros_like(est.fast.noise.moments))
    # a state written before the moments existed kept one variance per cell
    legacy = {k: v for k, v in state.items() if k != "ukf_noise_moments"}
    legacy["ukf_r_adapt"] = np.full(est.n, 4e-6)
    restored.set_state(legacy)
    np.testing.assert_array_equal(restored.ukf.r_adapt, np.full(est.n, 4e-6))
    # a state written before the innovation's autocorrelation was kept: the shape moments alone
    shape_only = {k: v for k, v in state.items() if not k.endswith("_noise_previous")}
    shape_only["ukf_noise_moments"] = state["ukf_noise_moments"][:, :N_SHAPE_MOMENTS]
    shape_only["fast_noise_moments"] = state["fast_noise_moments"][:, :N_SHAPE_MOMENTS]
    restored.set_state(shape_only)
    np.testing.assert_array_equal(restored.ukf.noise.moments[:, :N_SHAPE_MOMENTS],
                                  est.ukf.noise.moments[:, :N_SHAPE_MOMENTS])
    assert np.all(restored.ukf.noise.moments[:, N_SHAPE_MOMENTS:] == 0.0)
    assert np.all(restored.ukf.noise.previous == 0.0) and np.all(restored.fast.noise.previous == 0.0)


def test_correlation_moments_round_trip_to_the_same_next_step(nmc_profile) -> None:
    s = EstimatorSettings(adaptive_noise_samples=50, adaptive_noise_correlation_cap=30.0)
    est, _ = _warm_pack(nmc_profile, s)
    assert np.any(est.ukf.noise.previous != 0.0) and np.any(est.ukf.noise.moments[:, 5] != 0.0)
    restored = PackEstimator(nmc_profile, est.n, s, "multi")
    restored.set_state(est.get_state())
    v = np.full(est.n, 3.7)
    for e in (est, restored):
        e.step(1.0, 1.0, v, np.full(est.n, 25.0))
    np.testing.assert_array_equal(restored.soc, est.soc)
    np.testing.assert_array_equal(restored.ukf.noise.moments, est.ukf.noise.moments)


def test_soc_estimate_stays_inside_zero_one(nmc_profile) -> None:
    """DESIGN: SOC in [0, 1]; a voltage beyond either end of the table pins it to the end."""
    est = PackEstimator(nmc_profile, 2)
    est.start(np.array([0.98, 0.02]))
    ocv = nmc_profile.ocv_table()
    hi = float(ocv.ocv(np.array(1.0), 25.0)) + 0.3
    lo = float(ocv.ocv(np.array(0.0), 25.0)) - 0.3
    for _ in range(30):
        est.step(1.0, 0.0, np.array([hi, lo]), np.full(2, 25.0))
        assert np.all((est.soc >= 0.0) & (est.soc <= 1.0))
    assert est.soc[0] == 1.0 and est.soc[1] == 0.0


def _corrupt(state: dict, key: str, how: str) -> dict:
    st = {k: np.array(v, copy=True) for k, v in state.items()}
    if how == "nan":
        st[key] = st[key].astype(float)
        st[key].flat[0] = np.nan
    elif how == "inf":
        st[key].flat[-1] = np.inf
    elif how == "shape":
        st[key] = st[key][:-1]
    elif how == "missing":
        del st[key]
    return st


@pytest.mark.parametrize(
    "key, how",
    [
        ("ukf_x", "nan"),
        ("ukf_P", "inf"),
        ("ukf_hist", "nan"),
        ("ukf_x", "shape"),
        ("ukf_P", "shape"),
        ("ukf_gains", "shape"),
        ("fast_z", "nan"),
        ("fast_P", "shape"),
        ("slow_z", "shape"),
        ("slow_ring", "nan"),
        ("ukf_nis", "missing"),
        ("fast_D", "missing"),
        ("ukf_noise_moments", "nan"),
        ("ukf_noise_moments", "shape"),
        ("fast_noise_moments", "nan"),
        ("fast_noise_moments", "shape"),
        ("ukf_noise_previous", "nan"),
        ("fast_noise_previous", "shape"),
    ],
)
def test_set_state_rejects_bad_state(nmc_profile, key: str, how: str) -> None:
    est, _ = _warm_pack(nmc_profile, EstimatorSettings(slow_identifier=True), steps=30)  # every state part present
    good = est.get_state()
    before = est.get_state()
    with pytest.raises(ValueError, match=key):
        est.set_state(_corrupt(good, key, how))
    after = est.get_state()  # a rejected state changes nothing
    for k in before:
        np.testing.assert_array_equal(after[k], before[k], err_msg=k)


def test_set_state_rejects_other_pack_size_and_version(nmc_profile) -> None:
    est, _ = _warm_pack(nmc_profile, steps=20)
    state = est.get_state()
    with pytest.raises(ValueError):
        PackEstimator(nmc_profile, 4).set_state(state)
    with pytest.raises(ValueError, match="version"):
        est.set_state({**state, "state_version": np.array(99)})
    # the state carries its G-L memory: an estimator holding another length takes the state's ...
    other = PackEstimator(nmc_profile, 3, EstimatorSettings(memory_length=8))
    other.set_state(state)
    assert other.memory_length == est.memory_length
    np.testing.assert_array_equal(other.ukf.hist, est.ukf.hist)
    # ... and memory arrays that do not hold the length the state declares are refused
    with pytest.raises(ValueError, match="ukf_hist"):
        est.set_state({**state, "memory_length": np.array(8)})
    with pytest.raises(ValueError, match="memory_length"):
        est.set_state({**state, "memory_length": np.array(0)})


def test_set_state_rejection_is_atomic_for_counters(nmc_profile) -> None:
    est, _ = _warm_pack(nmc_profile, steps=30)
    before = est.get_state()
    bad = _corrupt(before, "reset_count", "shape")
    bad["ukf_x"] = bad["ukf_x"] + 0.01
    with pytest.raises(ValueError, match="reset_count"):
        est.set_state(bad)
    np.testing.assert_array_equal(est.get_state()["ukf_x"], before["ukf_x"])


# -- divergence ------------------------------------------------------------------------------------
def test_divergence_is_detected_and_cell_reinitialised(nmc_profile) -> None:
    N = 3
    current, voltage, temp, start, soc_true = _pack_data(nmc_profile, N, 400, seed=4)
    est = PackEstimator(nmc_profile, N, EstimatorSettings())
    est.start(start)
    for k in range(200):
        est.step(1.0 if k else 0.0, current[k], voltage[k], temp)
    assert not est.reset_count.any()
    # the divergence statistic is an EMA (2 % a sample) of the normalised innovation squared, and
    # under load the current-dependent model error widens the predicted spread: a few samples
    for k in range(200, 210):
        v = voltage[k].copy()
        v[2] = 9.0  # absurd
        est.step(1.0, current[k], v, temp)
        if est.reset_count[2]:
            break
    assert est.reset_count[2] >= 1
    assert est.reset_count[0] == est.reset_count[1] == 0
    assert est.ocv_initialised[2] and not est.ocv_initialised[:2].any()
    # re-initialised from the (absurd) voltage: SOC clipped to the table, σ back to the start value
    assert 0.0 <= est.soc[2] <= 1.0
    assert est.soc_std[2] > 0.05
    assert np.all(np.isfinite(est.ukf.x)) and np.all(np.isfinite(est.ukf.P))
    count, first_sane = est.reset_count[2], k + 1
    # sane data again: no further resets, the cell re-converges
    for k in range(first_sane, 400):
        est.step(1.0, current[k], voltage[k], temp)
    assert est.reset_count[2] == count
    assert est.soc_std[2] < 0.05
    assert abs(est.soc[2] - soc_true[-1, 2]) < 0.03


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")
def test_non_finite_filter_state_counts_as_divergence(nmc_profile) -> None:
    est = PackEstimator(nmc_profile, 2)
    est.start(np.array([0.5, 0.5]))
    est.step(1.0, 1.0, np.array([3.7, 3.7]), np.full(2, 25.0))
    est.ukf.x[0, 0] = np.nan
    est.step(1.0, 1.0, np.array([3.7, 3.7]), np.full(2, 25.0))
    assert est.reset_count.tolist() == [1, 0]
    assert np.all(np.isfinite(est.ukf.x))


# -- adaptive measurement noise (covariance matching) ---------------------------------------------
def _adapted_variance(profile, rec, settings: EstimatorSettings) -> tuple[float, np.ndarray]:
    data = load_recording(rec.path)
    est = PackEstimator(profile, 1, settings, "none")
    est.start(np.array([rec.soc_true[0]]))
    soc = np.empty(len(data))
    dt = data.dt_s()
    for k in range(len(data)):
        est.step(dt[k], data.current_a[k], data.voltage_v[k:k + 1], data.temperature_c[k:k + 1])
        soc[k] = est.soc[0]
    return float(est.ukf.r_adapt[0]), soc


def test_adaptive_noise_grows_only_when_the_model_is_wrong(nmc_recording, nmc_profile_factory) -> None:
    rec = nmc_recording(duration_s=1000, seed=3, soc0=0.8)
    # the fixed part of the noise model held at 0.02 V/A and 0.02 A on this 2 Ah cell for both runs, so the
    # comparison is what the adaptation adds to one base (a larger fixed per-C-rate term also leans on the
    # current integral under load, and on this cell reaches about the same SOC error without adapting)
    base = {"voltage_noise_per_c_v": 0.04, "current_noise_c": 0.01}
    on = EstimatorSettings(adaptive_noise_samples=100, **base)
    right, soc_right = _adapted_variance(nmc_profile_factory(), rec, on)
    # the filter's model has three times the true ohmic resistance: innovations under load
    # are far beyond the predicted spread, and the matched variance says so
    wrong, soc_wrong = _adapted_variance(nmc_profile_factory(r_ohm=0.06), rec, on)
    assert right < 0.003**2
    assert wrong > 10 * max(right, 1e-9) and wrong > 0.005**2
    off, soc_off = _adapted_variance(nmc_profile_factory(r_ohm=0.06), rec,
                                     EstimatorSettings(adaptive_noise_samples=0, **base))
    assert off == 0.0
    # leaning on the current integral keeps the wrong model's SOC closer to the truth
    err_on = np.sqrt(np.mean((soc_wrong - rec.soc_true) ** 2))
    err_off = np.sqrt(np.mean((soc_off - rec.soc_true) ** 2))
    assert err_on < err_off
    assert np.sqrt(np.mean((soc_right - rec.soc_true) ** 2)) < 0.01


# -- current-sensor offset state ---------------------------------------------------------------------
def _offset_run(rec, profile, settings: EstimatorSettings, offset_a: float):
    """foukf from a wrong start on ``rec`` with ``offset_a`` added to the current it reads."""
    import dataclasses

    recording = load_recording(rec.path)
    biased = dataclasses.replace(recording, current_a=recording.current_a + offset_a)
    return foukf(settings).run(biased, profile, 0.7)


def test_current_offset_state_learns_a_sensor_offset(nmc_recording, nmc_profile) -> None:
    """The model is exact here, so a drift of SOC against the OCV is the offset's alone: with
    the offset state the filter learns it (sign and size) and keeps SOC closer to the truth
    than the same filter without the state (80 min: the offset is learned in about the first 10, and
    the SOC is scored over the last 20)."""
    rec = nmc_recording(duration_s=4800, seed=3, soc0=0.9)
    offset = 0.03 * nmc_profile.capacity_ah
    on = EstimatorSettings(current_bias_state=True, current_bias_init_std_c=0.05)
    with_state = _offset_run(rec, nmc_profile, on, offset)
    without = _offset_run(rec, nmc_profile, EstimatorSettings(), offset)
    learned = with_state.params["current_bias_a"]
    assert learned[-1] == pytest.approx(offset, rel=0.3)
    assert "current_bias_a" not in without.params
    err_on = _rmse_after(with_state.soc - rec.soc_true, rec.time_s, 3600.0)
    err_off = _rmse_after(without.soc - rec.soc_true, rec.time_s, 3600.0)
    assert err_on < 0.5 * err_off, (err_on, err_off)


def test_current_offset_state_stays_near_zero_without_an_offset(nmc_recording, nmc_profile) -> None:
    # 40 min: four times what the state takes to learn a real offset (the test above)
    rec = nmc_recording(duration_s=2400, seed=3, soc0=0.9)
    on = EstimatorSettings(current_bias_state=True, current_bias_init_std_c=0.05)
    trace = _offset_run(rec, nmc_profile, on, 0.0)
    assert abs(trace.params["current_bias_a"][-1]) < 0.005 * nmc_profile.capacity_ah
    assert _rmse_after(trace.soc - rec.soc_true, rec.time_s) < 0.01


def test_current_offset_state_keeps_covariance_spd_and_batch_equal_to_single(nmc_profile) -> None:
    settings = EstimatorSettings(current_bias_state=True, slow_identifier=False, capacity_estimation="absolute")
    cells = [0, 77, 199]
    pack, singles = _batch_vs_single(nmc_profile, settings, cells)
    assert pack.ukf.P.shape[1] == pack.n_branches + 3
    P = pack.ukf.P
    assert np.allclose(P, np.swapaxes(P, 1, 2), atol=1e-12)
    assert (np.linalg.eigvalsh(0.5 * (P + np.swapaxes(P, 1, 2))) > 0).all()
    for c, one in zip(cells, singles):
        assert pack.soc[c] == pytest.approx(one.soc[0], rel=1e-9, abs=1e-10), c
        assert pack.ukf.current_bias_a[c] == pytest.approx(one.ukf.current_bias_a[0], rel=1e-7, abs=1e-12), c


# -- model error from the fit's residual ---------------------------------------------------------
def _with_fit_rmse(profile, rmse_mv: dict[float, float | None]):
    """``profile`` with a 2-RC section whose points carry these fit RMSEs (mV) per temperature."""
    from service.cell.profile import Ecm2RcPoint, Ecm2RcSpec

    points = [Ecm2RcPoint(temp_c=t, r0=0.02, r1=0.01, tau1_s=10.0, r2=0.01, tau2_s=100.0, fit_rmse_mv=r)
              for t, r in rmse_mv.items()]
    return profile.model_copy(update={"ecm2rc": Ecm2RcSpec(ocv=profile.ocv, points=points)})


def test_fit_rmse_is_linear_in_temperature_and_held_beyond(nmc_profile) -> None:
    spec = _with_fit_rmse(nmc_profile, {0.0: 30.0, 25.0: 10.0}).ecm2rc
    assert spec.fit_rmse_v_at(np.array([-20.0, 0.0, 12.5, 25.0, 40.0])) == pytest.approx(
        [0.030, 0.030, 0.020, 0.010, 0.010])
    assert _with_fit_rmse(nmc_profile, {0.0: 30.0, 25.0: None}).ecm2rc.fit_rmse_v_at(np.array([10.0])) is None


def test_model_error_follows_the_fit_rmse_at_each_cells_temperature(nmc_profile) -> None:
    profile = _with_fit_rmse(nmc_profile, {0.0: 30.0, 25.0: 10.0})
    pack = PackEstimator(profile, 2, EstimatorSettings(voltage_noise_per_fit_rmse=8.0))
    pack.start(np.array([0.5, 0.5]))
    pack.step(0.0, np.zeros(2), np.full(2, 3.7), np.array([25.0, 0.0]))
    assert pack.ukf.model_error_per_c_v == pytest.approx([0.08, 0.24])
    pack.step(1.0, np.zeros(2), np.full(2, 3.7), np.array([12.5, 0.0]))  # the first cell cools to 12.5 °C
    assert pack.ukf.model_error_per_c_v == pytest.approx([0.16, 0.24])
    # off by default, and without fit RMSEs the constant stands
    assert PackEstimator(profile, 2).ukf.model_error_per_c_v is None
    bare = PackEstimator(nmc_profile, 2, EstimatorSettings(voltage_noise_per_fit_rmse=8.0))
    assert bare.ukf.model_error_per_c_v is None


def test_fit_rmse_model_error_equal_to_the_constant_gives_the_same_estimate(nmc_profile) -> None:
    """k × RMSE equal to voltage_noise_per_c_v is the same filter: the per-C-rate error is applied
    at the cell's capacity either way."""
    profile = _with_fit_rmse(nmc_profile, {25.0: 20.0})
    base = EstimatorSettings(capacity_estimation="absolute")
    current, voltage, temp, start, _ = _pack_data(profile, 3, 200, seed=3)
    runs = []
    for settings in (base, base.model_copy(update={"voltage_noise_per_fit_rmse": base.voltage_noise_per_c_v / 0.020}),
                     base.model_copy(update={"voltage_noise_per_fit_rmse": 2 * base.voltage_noise_per_c_v / 0.020})):
        pack = PackEstimator(profile, 3, settings)
        pack.start(start)
        for k in range(200):
            pack.step(1.0 if k else 0.0, current[k], voltage[k], temp)
        runs.append(pack.soc.copy())
    assert runs[1] == pytest.approx(runs[0], rel=1e-12, abs=1e-12)
    assert not np.allclose(runs[2], runs[0], rtol=0, atol=1e-6)


# -- OCV-table error state ---------------------------------------------------------------------------
def _with_ocv_rows(profile, row):
    """``profile`` with each OCV row replaced by ``row(soc, ocv_v)`` (arrays on the table's SOC grid)."""
    soc = np.asarray(profile.ocv.soc)
    rows = [list(row(soc, np.asarray(r, float))) for r in profile.ocv.ocv_v]
    return profile.model_copy(update={"ocv": profile.ocv.model_copy(update={"ocv_v": rows})})


def _bumped_table(profile, bump_v: float):
    """``profile`` with its OCV table raised by ``bump_v`` between SOC 0.3 and 0.7 (a fitted table's
    local error), smoothly at the edges."""
    return _with_ocv_rows(profile, lambda soc, r: r + bump_v * np.clip(np.minimum(soc - 0.25, 0.75 - soc) / 0.05,
                                                                       0.0, 1.0))


def test_ocv_error_state_holds_soc_against_a_local_table_error(nmc_recording, nmc_profile) -> None:
    """A table 10 mV high over mid SOC pulls a filter that reads it as white noise off by its
    offset over the OCV slope; with the OCV-error state the persistent residual is taken up by the
    state and SOC stays closer to the truth.  On the exact table the state costs little (checked over
    the first hour, from a start 0.2 off).  The table-error comparison needs the whole two hours: the
    ratio grows toward its bar when the recording is cut or started lower."""
    rec = nmc_recording(duration_s=7200, seed=3, soc0=0.9)
    recording = load_recording(rec.path)
    wrong = _bumped_table(nmc_profile, 0.010)
    on = EstimatorSettings(ocv_error_std_v=0.01)
    err = {name: _rmse_after(fomiukf(s).run(recording, wrong, 0.9).soc - rec.soc_true, rec.time_s)
           for name, s in (("on", on), ("off", EstimatorSettings()))}
    assert err["on"] < 0.7 * err["off"], err
    hour = 3600
    exact = fomiukf(on).run(recording.slice(0, hour), nmc_profile, 0.7)
    assert _rmse_after(exact.soc - rec.soc_true[:hour], rec.time_s[:hour]) < 0.01


def test_ocv_error_state_is_off_by_default() -> None:
    from service.cell.ocv import OcvTable
    from service.estimators.fomiukf import FoMiUkf

    table = OcvTable.from_points(np.linspace(0, 1, 5), np.linspace(3.4, 4.2, 5))
    assert FoMiUkf(table, 2, 2, EstimatorSettings()).i_ocv is None
    with_state = FoMiUkf(table, 2, 2, EstimatorSettings(ocv_error_std_v=0.01, current_bias_state=True))
    assert (with_state.nx, with_state.i_ocv, with_state.i_bias) == (6, 5, 4)


def _flat_run_table(profile, lo: float, hi: float):
    """``profile`` with its OCV held flat over SOC [lo, hi] (as a monotone fit holds it where the
    data would have it fall)."""
    return _with_ocv_rows(profile, lambda soc, r: np.where((soc >= lo) & (soc <= hi), np.interp(lo, soc, r), r))


@pytest.mark.parametrize("soc, on_run", [(0.5, True), (0.2, False)])
def test_flat_ocv_noise_applies_on_a_flat_run_only(nmc_profile, soc: float, on_run: bool) -> None:
    """``flat_ocv_noise_v`` adds its variance to the innovation's where the table is flat at the
    filter's SOC, and nothing elsewhere; with it the SOC gain on the run shrinks."""
    profile = _flat_run_table(nmc_profile, 0.45, 0.55)
    out = {}
    for value in (0.0, 0.05):
        pack = PackEstimator(profile, 1, EstimatorSettings(flat_ocv_noise_v=value, adaptive_noise_samples=0,
                                                           fast_identifier=False))
        pack.start(soc, soc_std=0.02)
        v = float(profile.ocv_table().ocv(np.array([soc + 0.01]), 25.0)[0])
        pack.step(1.0, 0.0, np.array([v]), np.array([25.0]))
        out[value] = (float(pack.ukf.innovation_var[0]), abs(float(pack.ukf.gain[0, pack.ukf.i_soc])))
    extra = out[0.05][0] - out[0.0][0]
    if on_run:
        assert extra == pytest.approx(0.05**2, rel=1e-6)
        assert out[0.05][1] < 0.5 * out[0.0][1]
    else:
        assert extra == pytest.approx(0.0, abs=1e-12)
        assert out[0.05][1] == pytest.approx(out[0.0][1])
