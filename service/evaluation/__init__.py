"""Offline evaluation: truth SOC, metrics and the scoring protocol of DESIGN §7."""
