"""The choices ``socd fit`` offers for reading the OCV, kept free of the numerical imports so the
command line can be built without them (``socd run`` must not load scipy)."""

from __future__ import annotations

#: between neighbouring rests no further apart than this in SOC the OCV may be interpolated through them
#: (:func:`service.characterisation.ocv_sources.interpolate_between_rests`): a pulse test's 10 % steps,
#: with room for its pulses' own charge
REST_INTERP_MAX_GAP = 0.15
#: how the OCV between a temperature's rests is read when it is fitted jointly (``socd fit
#: --ocv-between-rests``): through the rests where they have settled, through them everywhere, or the
#: joint fit's shape shifted onto them (the default)
OCV_BETWEEN_RESTS = ("joint", "settled", "interpolate")
