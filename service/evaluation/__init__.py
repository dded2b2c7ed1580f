"""Offline evaluation (DESIGN §7): the scoring loop of ``socd evaluate`` (:mod:`.run`), its
metrics and plots.  The truth SOC it scores against is :mod:`service.cell.truth`."""
