"""Tuning of the paper's pipeline (FO-MI-UKF + fast and slow identifiers), validated by pydantic.

Defaults are the values ``socd evaluate`` scores best with on the bundled cells
(docs/results/soc_accuracy.md, docs/results/tuning.md).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.cell.memory import MAX_MEMORY_LENGTH
from service.strict_numbers import NoBooleanNumbers


def current_sigma_a(noise_a: float | None, noise_c: float, capacity_ah: np.ndarray) -> np.ndarray:
    """A current sensor's σ [A] for cells of ``capacity_ah``: ``noise_a`` where it is set (a value in
    A, e.g. from the sensor's datasheet), else ``noise_c`` × 1C. The one rule both filters use."""
    capacity = np.asarray(capacity_ah, dtype=float)
    return np.full_like(capacity, noise_a) if noise_a is not None else noise_c * capacity


class EstimatorSettings(NoBooleanNumbers, BaseModel):
    # a NaN or infinite setting is a mistake (a NaN UKF weight reset the filter at every step)
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    memory_length: int = Field(
        16, ge=1, le=MAX_MEMORY_LENGTH,
        description="G-L short-memory length L (Zeng Eq. 2) for a profile that does not carry the memory span "
        "it was fitted with (memory_span_s), or with memory_follows_sample_period off")
    memory_follows_sample_period: bool = Field(
        True,
        description="run the model with L = the profile's memory_span_s / the sample period, so a profile "
        "fitted on 1 s samples keeps its memory on a 10 Hz bus (service/cell/memory.py); off: L = memory_length")
    sample_period_s: float | None = Field(
        None, gt=0,
        description="the BMS's sample period for `socd run` (s); unset: the median of the first sample "
        "intervals the service sees. socd evaluate reads each recording's own")
    innovation_length: int = Field(
        1, ge=1, le=512,
        description="multi-innovation window (Zeng Eq. 18); 1 = single innovation, the default: cheaper, and "
        "the window of 4 gains nothing on the scored cells (docs/results/soc_accuracy.md); the 'fomiukf' "
        "evaluator uses 4 unless this is set above 1",
    )
    innovation_weighting: Literal["paper", "normalized"] = Field(
        "normalized",
        description="'paper': Σ F_i K_i e_i as in Zeng Eq. 20; 'normalized': weights sum to 1 so old "
        "innovations are not counted twice",
    )
    identifier_sees: Literal["single", "multi"] = Field(
        "single",
        description="which SOC-filter posterior the fast identifier's output uses with a multi-innovation "
        "window: 'single' = prior + K·e of this sample, the posterior its Table-1 sensitivity "
        "dx+/dθ = dx-/dθ - K·C describes; 'multi' = the multi-innovation posterior, which has taken only "
        "part of this innovation (the rest arrives over the next samples), so the identifier reads the "
        "untaken part as a parameter error. No effect with a single innovation",
    )
    fast_identifier: bool = Field(True, description="run the fast-rate EKF over [R_ohm, R_ct, C_dl, m, U_df]")
    fast_identifier_input: Literal["level", "difference"] = Field(
        "difference", description="'level': the voltage itself (Zeng Eq. 13); 'difference': sample-to-sample "
        "voltage change, which separates the fast dynamics from the OCV (and the SOC error), so the identifier "
        "does not chase a flat OCV plateau with R_ohm and R_ct"
    )
    slow_identifier: bool = Field(
        False, description="run the slow-rate EKF over [R_df, C_df, n]; off by default: in a pack it and the "
        "online capacity estimate explain the same voltage drift and pull each other off (docs/results/tuning.md)"
    )
    identify_below_soc_std: float = Field(
        0.02, gt=0, description="identifiers adapt a cell only once its SOC σ is below this (SOC and "
        "parameters are confounded while SOC is still converging)"
    )
    slow_soc_delta: float = Field(0.005, gt=0, le=0.5, description="SOC movement that triggers a slow update")
    voltage_noise_v: float = Field(0.01, gt=0, le=1, description="measurement noise σ of the SOC filter: sensor noise plus model error")
    voltage_noise_per_c_v: float = Field(
        0.222, ge=0, le=10, description="model error that grows with the C-rate: σ_v² = σ² + (k·|I|/Q)², Q the cell's "
        "capacity in Ah; per C-rate, not per amp, so a cell of any size (or cells in parallel) gets the same filter; "
        "chosen leave-one-cell-out (docs/results/tuning.md)"
    )
    voltage_noise_per_amp_v: float | None = Field(
        None, ge=0, le=10, description="the same model error per amp (σ_v² = σ² + (k·|I|)²); overrides voltage_noise_per_c_v"
    )
    voltage_noise_per_fit_rmse: float = Field(
        0.0, ge=0, le=1000, description="model error per C-rate as this multiple of the profile's 2-RC fit RMSE at the "
        "cell's temperature (σ per C-rate = k·RMSE_fit(T), V): a temperature the model fits poorly is trusted less "
        "under load; overrides voltage_noise_per_c_v and voltage_noise_per_amp_v when > 0 and the profile stores the "
        "2-RC fit's RMSEs ('socd fit' does); 0: those constants at every temperature. Swept leave-one-cell-out in "
        "docs/results/tuning.md, where it ties with the constant"
    )
    voltage_noise_rel_overpotential: float = Field(
        0.0, ge=0, le=10, description="model error as a fraction of the modelled overpotential "
        "|I|·(R_ohm + ΣR_b): scales with the cell's resistance at its temperature"
    )
    adaptive_noise_samples: int = Field(
        300, ge=0, le=100000,
        description="covariance matching of the measurement noise (adaptive UKF): the variance the innovations "
        "show beyond what the filter predicts is averaged over about this many samples and added to σ_v²; the "
        "filter then leans on the current integral where the model is poor (cold, near empty). The fast "
        "identifier matches its own innovations over the same window, so it moves its parameters less on "
        "model error than on information. 0 = off (both)",
    )
    adaptive_noise_shape: Literal["uniform", "load"] = Field(
        "uniform", description="'uniform': one adapted variance for every sample; 'load': a + c·(|I|·R_total)², "
        "so the model error learned under load does not drown the rests (service.estimators.adaptive_noise)",
    )
    adaptive_noise_correlation_cap: float = Field(
        1.0, ge=1, le=1000,
        description="the learned model-error variance is multiplied by the innovation's variance inflation factor "
        "(1+ρ)/(1-ρ), ρ its lag-1 autocorrelation over the same window, at most this: a model error that persists "
        "for minutes is counted as the few independent samples it is, not as fresh evidence every step (cold cells). "
        "1 = off. Shared by the fast identifier (service.estimators.adaptive_noise)",
    )
    current_noise_c: float = Field(
        0.0288, ge=0, le=10, description="σ of the current integral's error driving SOC process noise, as a fraction "
        "of 1C (the cell's capacity in A): scale-free, like voltage_noise_per_c_v. It stands for the sensor's "
        "noise and offset and the capacity's error together, so it is larger than a sensor's datasheet σ; "
        "chosen leave-one-cell-out with param_init_std_rel (docs/results/tuning.md)"
    )
    current_noise_a: float | None = Field(
        None, ge=0, le=1000, description="the current-sensor noise σ in A (e.g. from the sensor's datasheet); overrides "
        "current_noise_c"
    )
    branch_noise_v_per_sqrt_s: float = Field(
        1e-4, ge=0, le=1, description="random walk of the CPE branch voltages U_cd, U_df in the SOC filter (V/√s): "
        "how much model error the polarisation states may take up instead of SOC"
    )
    current_bias_state: bool = Field(
        False, description="augment the SOC filter with a current-sensor offset state b (A): SOC integrates "
        "I - b, b walks slowly; the offset is then learned from the voltage instead of drifting SOC. Off by "
        "default: on real cells it also takes up OCV-table error (docs/results/tuning.md)"
    )
    current_bias_init_std_c: float = Field(
        0.01, gt=0, le=1, description="σ of the offset state at a start, as a fraction of 1C (0.01 = 1 % of "
        "the capacity in A)"
    )
    current_bias_walk_c_per_sqrt_s: float = Field(
        1e-5, ge=0, le=1, description="random walk of the offset state, fraction of 1C per √s"
    )
    ocv_error_std_v: float = Field(
        0.0, ge=0, le=1, description="augment the SOC filter with an OCV-table error state (V) of this σ: a voltage "
        "offset the table makes at the present SOC, correlated over SOC, so a persistent residual at one SOC "
        "(a long rest on a table that is off there) is not read as evidence sample after sample. 0 = off "
        "(docs/results/tuning.md)"
    )
    ocv_error_soc_length: float = Field(
        0.05, gt=0, le=1, description="SOC distance over which the OCV-table error state decorrelates "
        "(ρ = exp(-|ΔSOC| / length) per step)"
    )
    reported_ocv_error_v: float = Field(
        0.01, ge=0, le=1, description="σ of the OCV table's error (V) that the published SOC σ allows for, "
        "correlated over ocv_error_soc_length of SOC; the filter does not estimate it, so SOC is unchanged "
        "(a consider analysis, service/estimators/consider.py). 0 with the rest: the filter's own σ, "
        "which counts every voltage sample as independent evidence. Chosen leave-one-cell-out "
        "(docs/results/tuning.md)"
    )
    reported_current_offset_c: float = Field(
        0.01, ge=0, le=1, description="σ of a current-sensor offset (fraction of 1C) that the published SOC σ "
        "allows for, the same way; e.g. a sensor's datasheet offset over the cell's 1C"
    )
    flat_ocv_noise_v: float = Field(
        0.1, ge=0, le=10, description="extra measurement σ (V) while SOC sits where the OCV table is flat "
        "(a run held flat by the monotone fit: the data there did not fix the OCV), so a rest on such a run is "
        "not read as evidence against the table; 0 = off. Chosen leave-one-cell-out (docs/results/tuning.md, "
        "loco_flat_ocv)")
    soc_init_std: float = Field(0.2, gt=0, le=1, description="σ of SOC at an OCV-based start")
    ukf_alpha: float = Field(
        1.0, gt=0, le=1, description="sigma-point spread (Zeng Table 3): the SOC points sit α·√n σ from the "
        "estimate, so at 1 the OCV is read across ± 2 σ of SOC (a secant over a flat plateau); chosen "
        "leave-one-cell-out against 0.5 and 0.2 (docs/results/tuning.md)")
    ukf_beta: float = Field(2.0, ge=0, le=100)
    # n + kappa must stay > 0 for the sigma points (n >= 3 states: two branches and SOC)
    ukf_kappa: float = Field(0.0, ge=-2.0, le=100.0)
    param_process_rel: float = Field(1e-4, ge=0, le=1, description="relative σ per step of parameter random walk (fast)")
    param_init_std_rel: float = Field(
        0.02, gt=0, le=1, description="the fast identifier's prior σ of the resistances and C_dl, relative to "
        "the profile's: how far it may move them in its first minutes; the random walk above then allows a slow "
        "drift. Chosen leave-one-cell-out with current_noise_c (docs/results/tuning.md)"
    )
    slow_param_process_rel: float = Field(2e-2, ge=0, le=1, description="relative σ per slow update (slow)")
    capacity_estimation: Literal["off", "pack-relative", "absolute"] = Field(
        "pack-relative",
        description="online capacity per cell (service.estimators.capacity, a dual EKF on the SOC filter's "
        "innovations): 'pack-relative' learns each cell against the pack's median cell (the profile's "
        "model error, common to the pack, cancels; a one-cell pack learns nothing), 'absolute' against the "
        "voltage alone, 'off' freezes the profile's capacity (results as without the estimator)",
    )
    capacity_init_std_rel: float = Field(0.05, gt=0, le=0.5, description="σ of a cell's capacity at start, "
                                         "relative to the profile's")
    capacity_bounds_rel: float = Field(0.3, gt=0, lt=1, description="the capacity stays within ± this "
                                       "fraction of the profile's")
    capacity_innovation_inflation: float = Field(
        10.0, ge=1, le=1e4, description="consecutive SOC-filter innovations that count as one independent sample "
        "for the capacity (model error correlates them)")
    capacity_walk_rel_per_sqrt_s: float = Field(1e-6, ge=0, le=1, description="random walk of the relative "
                                                "capacity, per √s (fade)")
    divergence_sigma: float = Field(8.0, gt=1, le=1e6, description="normalised innovation that counts as divergence")

    def current_noise_sigma_a(self, capacity_ah: np.ndarray) -> np.ndarray:
        """σ of the current sensor [A] for cells of ``capacity_ah`` (:func:`current_sigma_a`)."""
        return current_sigma_a(self.current_noise_a, self.current_noise_c, capacity_ah)

    def voltage_noise_per_amp(self, capacity_ah: np.ndarray) -> np.ndarray:
        """The current-dependent model error's slope [V/A] for cells of ``capacity_ah``."""
        if self.voltage_noise_per_amp_v is not None:
            return np.full_like(np.asarray(capacity_ah, dtype=float), self.voltage_noise_per_amp_v)
        return self.voltage_noise_per_c_v / np.asarray(capacity_ah, dtype=float)
