"""How ``socd fit`` shares the fractional model's shape across temperatures, kept free of the
numerical imports so the command line can be built without them (``socd run`` must not load scipy).

``each``: every temperature's search is free.  ``orders``: the CPE orders m, n of the reference
temperature's point (the one nearest 25 °C, fitted first) hold at every other temperature, so
only the resistances and time constants follow temperature.  ``orders-ratio``: the ratio of the
two branches' time constants holds as well.  With one order per branch the profile's
log-linear interpolation of R and C between fitted temperatures is the interpolation of the
time constants (tau^alpha = R C); with orders that differ between two points the cell between
them is read with a shape neither point has."""

from __future__ import annotations

SHAPES = ("each", "orders", "orders-ratio")
#: chosen leave-one-cell-out over nine cells and two optimiser seeds (docs/results/characterisation.md,
#: ``shape_seeds``): ``orders`` reads better than ``each`` by more than twice its paired standard error; on
#: one seed alone the two were within it (``unseen_shape``)
DEFAULT_SHAPE = "orders"
