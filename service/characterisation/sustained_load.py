"""The polarisation a fitted point gives under a sustained load: what searches that fit the
recordings equally well can still disagree on.

Pulse tests fix the fast dynamics and leave the slow branch's DC resistance loosely bound: two
searches can fit an HPPC test to within a fraction of a millivolt and still predict voltages tens of
millivolts apart after ten minutes of steady discharge, which is what a drive cycle asks of the model.
:func:`sustained_polarisation_mv` reads that prediction, the same way for every candidate point.
"""

from __future__ import annotations

import numpy as np

from service.cell.profile import CellProfile, HysteresisSpec, ParameterPoint
from service.cell.trajectory import simulate_batch
from service.cell.units import SECONDS_PER_HOUR

#: the load: 1C discharge for ten minutes from rest at 60 % SOC, at the point's own temperature
SUSTAINED_C_RATE = 1.0
SUSTAINED_S = 600
SUSTAINED_SOC0 = 0.6


def one_point_profile(template: CellProfile, point: ParameterPoint, hysteresis: HysteresisSpec) -> CellProfile:
    """``template`` with ``point`` (labelled 25 °C) as its only parameter point and ``hysteresis``: the
    profile a fit simulates one candidate point with, at whatever temperature it is asked for."""
    return template.model_copy(update={"parameters": [point.model_copy(update={"temp_c": 25.0})],
                                       "hysteresis": hysteresis})


def sustained_polarisation_mv(template: CellProfile, point: ParameterPoint, hysteresis: HysteresisSpec,
                              memory_length: int) -> float:
    """OCV at the counted SOC minus the model's voltage [mV] after :data:`SUSTAINED_S` seconds of
    :data:`SUSTAINED_C_RATE` discharge from rest at :data:`SUSTAINED_SOC0`, simulated at 1 s steps with
    ``point`` at its temperature (the model :func:`simulate_batch` runs for a fit: ohmic drop, both CPE
    branches, the Butler-Volmer term) and ``template``'s OCV and capacity."""
    prof = one_point_profile(template, point, hysteresis)
    time_s = np.arange(SUSTAINED_S + 1, dtype=float)
    current_a = np.full_like(time_s, SUSTAINED_C_RATE * prof.effective_capacity_ah)
    current_a[0] = 0.0
    temp_c = np.full_like(time_s, point.temp_c)
    v, _ = simulate_batch(prof, time_s, current_a, temp_c, np.array([SUSTAINED_SOC0]),
                          prof.parameters_at(point.temp_c, n_cells=1), memory_length=memory_length)
    soc_end = SUSTAINED_SOC0 - SUSTAINED_C_RATE * SUSTAINED_S / SECONDS_PER_HOUR
    ocv_end = float(prof.ocv_table().ocv(np.array([soc_end]), point.temp_c)[0])
    return 1000.0 * (ocv_end - float(v[-1, 0]))
