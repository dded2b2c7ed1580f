"""A pydantic base for settings and profiles read from TOML: a boolean is never a number.

pydantic's lax mode reads ``true`` as 1 in an int or float field, so ``current_sign = true`` in a
config flipped the current convention, ``n_cells = true`` made a one-cell pack and
``capacity_ah = true`` a 1 Ah cell, each without a word.  Strings still convert (``"96"`` is 96):
environment overrides (``SOCD_PACK__N_CELLS=96``) arrive as strings.  The same holds inside lists
and tuples of numbers (an OCV row, a plausibility range).
"""

from __future__ import annotations

from types import UnionType
from typing import Any, Union, get_args, get_origin

from pydantic import BaseModel, model_validator


class NoBooleanNumbers(BaseModel):
    """Refuses a boolean given for an int or float field, naming the field."""

    @model_validator(mode="before")
    @classmethod
    def _no_boolean_numbers(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for name, value in data.items():
                field = cls.model_fields.get(name)
                if field is not None and holds_numbers(field.annotation) and contains_boolean(value):
                    raise ValueError(f"{name} = {str(value).lower()}: a number is expected, not a boolean"
                                     if isinstance(value, bool) else f"{name}: numbers are expected, and it holds a boolean")
        return data


def is_number(annotation: Any) -> bool:
    """An int or float field, optional or not (a bool or ``int | bool`` field takes booleans)."""
    if get_origin(annotation) not in (None, Union, UnionType):
        return False  # a container
    kinds = get_args(annotation) or (annotation,)
    return bool not in kinds and any(k in (int, float) for k in kinds)


def holds_numbers(annotation: Any) -> bool:
    """A number field, or a list or tuple (nested, optional) of numbers."""
    if is_number(annotation):
        return True
    if get_origin(annotation) not in (list, tuple, Union, UnionType):
        return False
    args = [a for a in get_args(annotation) if a not in (Ellipsis, type(None))]
    return bool(args) and all(holds_numbers(a) for a in args)


def contains_boolean(value: Any) -> bool:
    """A boolean anywhere inside nested lists and tuples."""
    if isinstance(value, bool):
        return True
    return isinstance(value, list | tuple) and any(contains_boolean(v) for v in value)
