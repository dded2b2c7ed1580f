"""Research tools around the product, not part of it (not in the wheel): validation grids on
simulated and PyBaMM recordings, clean twins of the labelled files, the diagnose → evaluate round
trip, leave-one-out tuning, rest checks of the truth SOC and the README's result tables.

Run from a source checkout, e.g. ``python -m research.clean_twin``; PyBaMM comes with the
``research`` extra (``pip install -e .[research]``).  ``service`` and ``replay`` never import
this package.
"""
