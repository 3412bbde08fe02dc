"""Enums for command-line choices, with one ``from_string`` that names the bad value and the valid ones."""
from __future__ import annotations

from enum import Enum
from typing import TypeVar

from edge_landing.runtime.core.errors import EdgeError, InputError

_C = TypeVar("_C", bound="ChoiceEnum")


class ChoiceEnum(str, Enum):
    """A string enum for a user-facing choice.

    ``from_string`` is case-insensitive and raises ``_error`` (InputError by default) with a message like
    ``unsupported world style 'x'; expected one of: suburban, urban``. Subclasses name the choice in ``_label``.
    """

    @classmethod
    def _label(cls) -> str:
        return cls.__name__

    @classmethod
    def _error(cls) -> type:
        return InputError

    @classmethod
    def from_string(cls: type[_C], value: str) -> _C:
        if isinstance(value, cls):
            return value
        text = str(value)
        for member in cls:
            if member.value == text or member.value.lower() == text.lower():
                return member
        error: type[EdgeError] = cls._error()
        raise error(f"unsupported {cls._label()} '{value}'; expected one of: "
                    f"{', '.join(m.value for m in cls)}") from None

    def __str__(self) -> str:
        value: str = self.value
        return value
