"""Error types shared across the package, kept apart from the command line so that a library
module (recordings, truth SOC) can raise them without importing ``service.cli``."""

from __future__ import annotations


class UserError(Exception):
    """A problem with the user's input: printed as one clear line, exit status 2."""
