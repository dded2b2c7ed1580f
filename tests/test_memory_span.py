"""The G-L short memory keeps the profile's span at any sample period (service/cell/memory.py).

A profile fitted on 1 s samples and run at 10 Hz with the same memory *length* keeps a tenth of
its memory, and its fractional branches become other branches.  These tests run the bundled
recording at its own 1 s period and held at 10 Hz: the model, the SOC filter and the service.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from daemon_support import run_daemon

from replay.pack import SpreadSpec, pack_frames
from service.cell.coulomb import coulomb_soc
from service.cell.memory import MAX_MEMORY_LENGTH, memory_length_at, sample_period_s
from service.cell.profile import CellProfile, load_profile
from service.cell.trajectory import simulate
from service.config import DEFAULT_CELL_PROFILE, DEFAULT_INPUT_DBC, DEFAULT_OUTPUT_DBC, build_config
from service.estimators.pipeline import PackEstimator, fomiukf
from service.estimators.settings import EstimatorSettings
from service.recording import Recording, load_recording

ROOT = Path(__file__).resolve().parents[1]
RECORDING = ROOT / "service" / "data" / "pan18650pf_25C_US06.csv"  # bundled: always present
FAST_S = 0.1


def fractional_profile() -> CellProfile:
    """The bundled profile with clearly fractional orders at every temperature (its 25 °C point
    has orders 1, where the memory beyond one sample holds nothing)."""
    prof = load_profile(DEFAULT_CELL_PROFILE)
    assert prof.memory_span_s is not None
    return prof.model_copy(update={"parameters": [p.model_copy(update={"m": 0.55, "n": 0.9})
                                                  for p in prof.parameters]})


def held_at(rec: Recording, period_s: float) -> Recording:
    """``rec`` (1 s samples) at ``period_s``: each sample's current and temperature held over the
    interval before it (the backward zero-order hold the model integrates), voltage left NaN."""
    k = round(1.0 / period_s)
    assert np.all(np.diff(rec.time_s) == 1.0), "the slice must be evenly sampled at 1 s"
    t = rec.time_s[0] + period_s * np.arange((len(rec) - 1) * k + 1)

    def hold(x: np.ndarray) -> np.ndarray:
        return np.concatenate([[x[0]], np.repeat(x[1:], k)])

    return Recording(rec.path, t, hold(rec.current_a), np.full(t.size, np.nan), hold(rec.temperature_c))


@pytest.fixture(scope="module")
def drive() -> Recording:
    return load_recording(RECORDING).slice(0, 601)  # 10 minutes of US06 from full charge, every 1 s


def test_memory_length_follows_the_span() -> None:
    assert memory_length_at(16.0, 1.0, 16) == 16
    assert memory_length_at(16.0, 0.1, 16) == 160
    assert memory_length_at(1.6, 1.0, 16) == 2
    assert memory_length_at(16.0, 0.001, 16) == MAX_MEMORY_LENGTH
    assert memory_length_at(None, 0.1, 16) == 16  # a profile from before the span was stored
    assert memory_length_at(16.0, None, 12) == 12
    assert sample_period_s(np.array([0.0, 0.1, 0.2, 60.2, 60.3])) == pytest.approx(0.1)


def test_the_span_keeps_the_model_at_another_sample_period(drive: Recording) -> None:
    prof = fractional_profile()
    v1, _ = simulate(prof, drive.time_s, drive.current_a, drive.temperature_c, 1.0, memory_length=16)
    fast = held_at(drive, FAST_S)
    rms = {}
    for label, length in (("span", memory_length_at(prof.memory_span_s, FAST_S, 16)), ("samples", 16)):
        v10, _ = simulate(prof, fast.time_s, fast.current_a, fast.temperature_c, 1.0, memory_length=length)
        rms[label] = 1000 * float(np.sqrt(np.mean((v10[::10] - v1) ** 2)))
    print(f"\nmodel at 10 Hz vs at 1 s, RMS mV: memory as a span {rms['span']:.2f}, as 16 samples {rms['samples']:.1f}")
    assert rms["span"] < 2.0
    assert rms["samples"] > 10.0  # the control: the same length in samples is another model


def _consistent_10hz(prof: CellProfile, drive: Recording) -> Recording:
    """The drive at 10 Hz with the voltage the profile's model gives there (its span kept) and
    the coulomb-counted truth."""
    fast = held_at(drive, FAST_S)
    length = memory_length_at(prof.memory_span_s, FAST_S, 16)
    v, _ = simulate(prof, fast.time_s, fast.current_a, fast.temperature_c, 1.0, memory_length=length)
    soc = coulomb_soc(fast.time_s, fast.current_a, prof.effective_capacity_ah, 1.0)
    return Recording(fast.path, fast.time_s, fast.current_a, v, fast.temperature_c, soc)


def test_the_filter_keeps_a_1s_profile_at_10hz(drive: Recording) -> None:
    prof = fractional_profile()
    rec = _consistent_10hz(prof, drive.slice(0, 401))  # 400 s: the last 100 s are scored
    est = PackEstimator(prof, 1, EstimatorSettings(), sample_period_s=sample_period_s(rec.time_s))
    assert est.memory_length == 160
    err = {}
    for label, follows in (("span", True), ("samples", False)):
        settings = EstimatorSettings(memory_follows_sample_period=follows, fast_identifier=False)
        trace = fomiukf(settings).run(rec, prof, 0.9)  # started 10 % off
        late = rec.time_s - rec.time_s[0] > 300
        err[label] = 100 * float(np.sqrt(np.mean((trace.soc[late] - rec.soc_true[late]) ** 2)))
    print(f"\nfomiukf at 10 Hz on a 1 s profile, SOC RMSE after 300 s: memory as a span {err['span']:.2f} %, "
          f"as 16 samples {err['samples']:.2f} %")
    assert err["span"] < 0.5
    assert err["samples"] > 2 * err["span"]  # the control


def test_the_service_learns_its_sample_period_and_checkpoints_the_memory(tmp_path: Path, drive: Recording) -> None:
    prof = load_profile(DEFAULT_CELL_PROFILE)
    rec = drive.slice(0, 61)
    fast = held_at(rec, FAST_S)
    fast = Recording(fast.path, fast.time_s, fast.current_a,
                     np.interp(fast.time_s, rec.time_s, rec.voltage_v), fast.temperature_c)
    cfg = build_config({
        "cell_profile": str(DEFAULT_CELL_PROFILE),
        "dbc": {"input": str(DEFAULT_INPUT_DBC), "output": str(DEFAULT_OUTPUT_DBC)},
        "pack": {"n_cells": 4},
        "bus": {"interface": "virtual", "channel": f"memory-span-{time.monotonic_ns()}"},
        "output": {"zenoh_enabled": False, "can_enabled": False},
        "estimator": {"slow_identifier": True},
        "checkpoint": {"path": str(tmp_path / "span.ckpt")},
    })
    frames, _ = pack_frames(fast, cfg, prof, 4, SpreadSpec(), seed=1, start_soc=1.0)
    d = run_daemon(cfg, frames)
    assert d.steps > 500
    assert d.estimator.memory_length == memory_length_at(prof.memory_span_s, FAST_S, 16) == 160
    state = d.estimator.get_state()
    # a service restarted from that checkpoint holds the same memory before it has seen a sample
    fresh = PackEstimator(prof, 4, cfg.estimator)
    assert fresh.memory_length == 16
    fresh.set_state(state)
    assert fresh.memory_length == 160
    np.testing.assert_array_equal(fresh.ukf.hist, d.estimator.ukf.hist)
    np.testing.assert_array_equal(fresh.slow.ring, d.estimator.slow.ring)
    # told its period, it starts with that memory
    told = PackEstimator(prof, 4, cfg.estimator.model_copy(update={"sample_period_s": FAST_S}),
                         sample_period_s=FAST_S)
    assert told.memory_length == 160
