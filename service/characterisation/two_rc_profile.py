"""A cell profile whose fractional points are its own textbook 2-RC points.

``socd fit`` stores the textbook 2-RC model beside the fractional one
(:class:`service.cell.profile.Ecm2RcSpec`).  Written in the fractional form (both CPE orders 1,
``C = τ/R``: :func:`service.characterisation.characterise.ecm_start_point`) with the hysteresis
off, it runs through the same simulator and filter as the fractional model, which separates what
the fractional fit gains from what the filter does (``socd fit --plots``,
``python -m research.two_rc_point``).
"""

from __future__ import annotations

from service.cell.profile import CellProfile, HysteresisSpec, ParameterPoint
from service.characterisation.characterise import ecm_start_point

#: temperatures closer than this [°C] are the same point
SAME_TEMP_C = 0.1


def with_two_rc_points(profile: CellProfile, temps_c: list[float] | None = None) -> CellProfile:
    """``profile`` with the fractional point at each of ``temps_c`` (None: all) set to its 2-RC point."""
    if profile.ecm2rc is None:
        raise ValueError(f"profile '{profile.name}' has no 2-RC fit (fit it with a current `socd fit`)")
    ecm_points = profile.ecm2rc.points
    wanted = [e.temp_c for e in ecm_points] if temps_c is None else temps_c
    points: list[ParameterPoint] = []
    replaced = []
    for point in profile.parameters:
        if any(abs(point.temp_c - t) < SAME_TEMP_C for t in wanted):
            ecm = next((e for e in ecm_points if abs(e.temp_c - point.temp_c) < SAME_TEMP_C), None)
            if ecm is None:
                raise ValueError(f"profile '{profile.name}' has no 2-RC point at {point.temp_c:g} °C")
            point = ecm_start_point(ecm, point.temp_c, linear_kinetics=point.i0_a is not None)
            replaced.append(point.temp_c)
        points.append(point)
    missing = [t for t in wanted if not any(abs(t - r) < SAME_TEMP_C for r in replaced)]
    if missing:
        raise ValueError(f"profile '{profile.name}' has no fractional point at {', '.join(f'{t:g}' for t in missing)} °C")
    return profile.model_copy(update={
        "parameters": points,
        "hysteresis": HysteresisSpec(table_branch=profile.hysteresis.table_branch),
    })
