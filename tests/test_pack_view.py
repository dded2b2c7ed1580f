"""The pack view (service.estimators.pack_view) on hand-made packs with known answers, and its
``SOCD_PackUsable`` frame decoded by cantools from the shipped ``dbc/socd_output.dbc``."""

from __future__ import annotations

from pathlib import Path

import cantools
import numpy as np
import pytest

from service.bus.encoder import OutputEncoder
from service.bus.types import PackSnapshot
from service.cell.ocv import GRID_POINTS, OcvTable
from service.cell.profile import load_profile
from service.config import DEFAULT_CELL_PROFILE, build_config
from service.estimators.pack_view import OcvEnergy, pack_view

ROOT = Path(__file__).resolve().parents[1]
#: OcvTable rows rise by at least 1 µV a grid step (make_monotone): a straight row gains that much slope
LIFT = 1e-6 * (GRID_POINTS - 1)
#: OCV = 3.0 + (1.2 + LIFT)·SOC V, so ∫_0^s OCV = 3.0 s + (0.6 + LIFT/2) s² (V per unit SOC; × Ah = Wh)
LINEAR = OcvEnergy(OcvTable.from_points(np.array([0.0, 1.0]), np.array([3.0, 4.2])))


def e_lin(s: float) -> float:
    return 3.0 * s + (0.6 + LIFT / 2) * s * s


def test_three_cell_pack_known_answer() -> None:
    soc = np.array([0.5, 0.8, 0.6])
    cap = np.array([2.0, 2.0, 1.0])
    v = pack_view(soc, cap, LINEAR)
    # charge held 1.0 / 1.6 / 0.6 Ah, room 1.0 / 0.4 / 0.4 Ah
    assert v.usable_discharge_ah == pytest.approx(0.6) and v.weakest_cell == 2
    assert v.usable_charge_ah == pytest.approx(0.4) and v.fullest_cell == 1  # tie 1/2: the first
    assert v.usable_soc == pytest.approx(0.6 / (0.6 + 0.4))
    assert v.imbalance_ah == pytest.approx(1.6 - 0.6)
    assert (v.soc_min, v.soc_mean, v.soc_max) == pytest.approx((0.5, 1.9 / 3, 0.8))
    assert (v.cell_min, v.cell_max, v.n_used, v.n_cells) == (0, 1, 3, 3)
    stored = 2 * e_lin(0.5) + 2 * e_lin(0.8) + 1 * e_lin(0.6)
    assert v.remaining_energy_wh == pytest.approx(stored, rel=1e-12)
    # every cell gives the weakest cell's 0.6 Ah: 0.5 -> 0.2, 0.8 -> 0.5, 0.6 -> 0
    usable = 2 * (e_lin(0.5) - e_lin(0.2)) + 2 * (e_lin(0.8) - e_lin(0.5)) + e_lin(0.6)
    assert v.usable_energy_wh == pytest.approx(usable, rel=1e-12)


def test_balanced_pack_usable_soc_is_the_cells_soc() -> None:
    v = pack_view(np.full(12, 0.37), 2.9, LINEAR)
    assert v.usable_soc == pytest.approx(0.37) and v.imbalance_ah == pytest.approx(0.0, abs=1e-12)
    assert v.remaining_energy_wh == pytest.approx(12 * 2.9 * e_lin(0.37))
    assert v.usable_energy_wh == pytest.approx(v.remaining_energy_wh)


def test_capacity_array_decides_the_weakest_cell() -> None:
    # same SOC, one faded cell: it holds the least charge and has the least room
    cap = np.array([3.0, 3.0, 2.4, 3.0])
    v = pack_view(np.full(4, 0.5), cap, LINEAR)
    assert v.weakest_cell == 2 and v.fullest_cell == 2
    assert v.usable_discharge_ah == pytest.approx(1.2) and v.usable_charge_ah == pytest.approx(1.2)
    assert v.usable_soc == pytest.approx(0.5) and v.imbalance_ah == pytest.approx(1.5 - 1.2)


def test_cells_left_out_keep_their_indices() -> None:
    soc = np.array([np.nan, 0.9, 0.2, 0.6, 0.1])
    cap = np.array([2.0, 2.0, 2.0, np.nan, 2.0])
    valid = np.array([True, True, True, True, False])
    v = pack_view(soc, cap, LINEAR, valid=valid)
    assert v.n_used == 2 and v.weakest_cell == 2 and v.fullest_cell == 1
    assert v.usable_soc == pytest.approx(0.4 / (0.4 + 0.2))
    none = pack_view(np.array([np.nan, np.nan]), 2.0, LINEAR)
    assert not none.ok and none.weakest_cell is None and np.isnan(none.usable_soc)


def test_a_pack_that_cannot_move_has_no_usable_soc() -> None:
    v = pack_view(np.array([1.0, 0.0]), 2.0, LINEAR)  # one full, one empty: no way in or out
    assert v.usable_discharge_ah == 0.0 and v.usable_charge_ah == 0.0 and np.isnan(v.usable_soc)
    assert v.imbalance_ah == pytest.approx(2.0) and v.usable_energy_wh == 0.0


def test_soc_outside_unit_interval_is_clipped() -> None:
    v = pack_view(np.array([1.02, -0.01]), 1.0, LINEAR)
    assert (v.soc_max, v.soc_min) == (1.0, 0.0)
    assert v.remaining_energy_wh == pytest.approx(e_lin(1.0))


def test_energy_interpolates_between_temperature_rows() -> None:
    table = OcvTable.from_points(np.array([0.0, 1.0]), np.array([[3.0, 4.0], [3.4, 4.2]]), np.array([0.0, 40.0]))
    e = OcvEnergy(table)
    # at 20 °C the OCV is 3.2 + (0.9 + LIFT) s: ∫_0^0.5 = 1.6 + (0.9 + LIFT) / 8
    assert e.integral(np.array([0.5]), np.array([20.0]))[0] == pytest.approx(1.6 + (0.9 + LIFT) / 8, rel=1e-12)
    below = e.integral(np.array([0.5]), np.array([-10.0]))[0]  # the nearest row holds: 3.0 + (1 + LIFT) s
    assert below == pytest.approx(1.5 + (1.0 + LIFT) / 8, rel=1e-12)


def test_energy_is_the_integral_of_the_profile_ocv() -> None:
    profile = load_profile(DEFAULT_CELL_PROFILE)
    table = profile.ocv_table()
    e = OcvEnergy(table)
    for temp in (-10.0, 10.0, 25.0):
        for s in (0.0, 0.0137, 0.5, 0.77, 1.0):
            grid = np.linspace(0.0, s, 20001)
            ocv = table.ocv(grid, temp)
            numeric = float(np.sum(0.5 * (ocv[1:] + ocv[:-1]) * np.diff(grid)))
            assert e.integral(np.array([s]), np.array([temp]))[0] == pytest.approx(numeric, abs=1e-6)


def test_pack_usable_frame_round_trips_through_the_shipped_dbc() -> None:
    db = cantools.database.load_file(str(ROOT / "dbc" / "socd_output.dbc"))
    msg = db.get_message_by_frame_id(2566870245)
    assert msg.name == "SOCD_PackUsable" and msg.is_extended_frame and msg.frame_id == 0x18FF54E5
    n = 96
    soc = np.linspace(0.3, 0.7, n)
    cap = np.full(n, 2.9)
    cap[17] = 2.5
    view = pack_view(soc, cap, LINEAR)
    snap = PackSnapshot(t_s=5.0, soc=soc, soc_std=np.full(n, 0.01), voltage_v=np.full(n, 3.7), pack=view)
    enc = OutputEncoder(build_config({}))
    frames = [f for f in enc.encode(snap, cells=False, params=False) if f.arbitration_id == 0x18FF54E5]
    assert len(frames) == 1 and frames[0].is_extended_id
    got = msg.decode(bytes(frames[0].data))
    assert got["SOCD_UsableSoc"] == pytest.approx(100 * view.usable_soc, abs=0.005)
    assert got["SOCD_RemainingEnergy"] == round(view.remaining_energy_wh)
    assert got["SOCD_ImbalanceAh"] == pytest.approx(view.imbalance_ah, abs=0.0005)
    assert got["SOCD_WeakestCell"] == view.weakest_cell == 0  # 0.3 × 2.9 < the faded cell's 0.34 × 2.5
    assert got["SOCD_PackUsableValid"] == 1
    # no estimate yet: the frame still goes out, its valid bit clear
    empty = PackSnapshot(t_s=5.0, soc=soc, soc_std=np.full(n, 0.01), voltage_v=np.full(n, 3.7))
    (f,) = [f for f in enc.encode(empty, cells=False, params=False) if f.arbitration_id == 0x18FF54E5]
    assert msg.decode(bytes(f.data))["SOCD_PackUsableValid"] == 0


def test_encoder_without_the_message_in_a_user_dbc() -> None:
    db = cantools.database.load_file(str(ROOT / "dbc" / "socd_output.dbc"))
    older = cantools.database.Database(messages=[m for m in db.messages if m.name != "SOCD_PackUsable"])
    enc = OutputEncoder(db=older)
    snap = PackSnapshot(t_s=1.0, soc=np.full(3, 0.5), soc_std=np.full(3, 0.01), voltage_v=np.full(3, 3.7),
                        pack=pack_view(np.full(3, 0.5), 2.0, LINEAR))
    assert len(enc.encode(snap)) == 2 * 3 + 2 and enc.errors == 0
