"""A pydantic base for settings and profiles read from TOML: a boolean is never a number.

pydantic's lax mode reads ``true`` as 1 in an int or float field, so ``current_sign = true`` in a
config flipped the current convention, ``n_cells = true`` made a one-cell pack and
``capacity_ah = true`` a 1 Ah cell, each without a word.  Strings still convert (``"96"`` is 96):
environment overrides (``SOCD_PACK__N_CELLS=96``) arrive as strings.
"""

from __future__ import annotations

from typing import Any, get_args

from pydantic import BaseModel, model_validator


class NoBooleanNumbers(BaseModel):
    """Refuses a boolean given for an int or float field, naming the field."""

    @model_validator(mode="before")
    @classmethod
    def _no_boolean_numbers(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for name, value in data.items():
                field = cls.model_fields.get(name)
                if isinstance(value, bool) and field is not None and is_number(field.annotation):
                    raise ValueError(f"{name} = {str(value).lower()}: a number is expected, not a boolean")
        return data


def is_number(annotation: Any) -> bool:
    """An int or float field, optional or not (a bool or ``int | bool`` field takes booleans)."""
    kinds = get_args(annotation) or (annotation,)
    return bool not in kinds and any(k in (int, float) for k in kinds)
