"""The choices ``socd fit`` offers for reading the OCV, kept free of the numerical imports so the
command line can be built without them (``socd run`` must not load scipy)."""

from __future__ import annotations

#: between neighbouring rests no further apart than this in SOC the OCV may be interpolated through them
#: (:func:`service.characterisation.ocv_sources.interpolate_between_rests`): a pulse test's 10 % steps,
#: with room for its pulses' own charge
REST_INTERP_MAX_GAP = 0.15
#: ``near-reference`` reads the OCV through the rests at temperatures within this of the fit's reference
#: temperature (the one nearest 25 °C), K: in the cold the joint table carries polarisation the model
#: does not, and the rests' own OCV there scored worse on two of four cells
NEAR_REFERENCE_K = 15.0
#: how the OCV between a temperature's rests is read when it is fitted jointly (``socd fit
#: --ocv-between-rests``): through the rests near the reference temperature (the default), the joint
#: fit's shape shifted onto them, through the rests where they have settled, everywhere, or near the
#: reference as the default does and in the cold as the reference temperature's finished row shifted
#: through that temperature's rests (the joint fit's shape there carries polarisation, the reference's
#: row does not)
OCV_BETWEEN_RESTS = ("near-reference", "joint", "settled", "interpolate", "reference-shape")
#: the default, chosen leave-one-cell-out over the Panasonic cell and the three PyBaMM cells fitted from
#: pulse tests alone (docs/results/characterisation.md, table ``loco_ocv_between_rests``)
DEFAULT_OCV_BETWEEN_RESTS = "near-reference"
#: weight of the second-difference penalty on a jointly fitted OCV (``socd fit --ocv-smoothing``;
#: :func:`service.characterisation.ecm2rc_fit.fit_ecm2rc`). Larger weights give a smoother table with
#: fewer flat steps; at 1 both filters read the Panasonic HPPC-alone drives at 25 °C worse, the
#: rests there anchoring the table every 10 % of SOC (``joint_ocv_smoothing`` in
#: docs/results/characterisation.md)
OCV_SMOOTH_WEIGHT = 0.01
