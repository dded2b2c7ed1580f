"""Unit conversions shared by the model, the estimators and the tools (one definition each)."""

from __future__ import annotations

#: seconds in an hour: charge in A·s over this is A·h; times in s over this are hours
SECONDS_PER_HOUR = 3600.0
