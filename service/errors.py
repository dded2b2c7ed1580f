"""Error types shared across the package, kept apart from the command line so that a library
module (recordings, truth SOC) can raise them without importing ``service.cli``."""

from __future__ import annotations

from typing import Any


class UserError(Exception):
    """A problem with the user's input: printed as one clear line, exit status 2."""


class MissingExtra(UserError):
    """What was asked for needs an optional extra that is not installed (its message ends in the
    ``pip install`` that adds it): printed as one line, exit status 3, as the README promises."""


def validation_message(error: Any) -> str:
    """One pydantic error's message (an entry of ``ValidationError.errors()``), without the
    ``Value error, `` pydantic puts before the text of a ValueError a validator raised."""
    return error["msg"].removeprefix("Value error, ")
