"""Strict checks of the values a network part reads itself (``conf/model``), naming the key.

A float, even ``32.0``, is never a size; a boolean is not a size either.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

__all__ = ["require_int", "require_nonnegative", "require_switch"]


def _kind(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"


def require_int(key: str, value: Any, minimum: int = 1) -> int:
    """``value`` as an ``int`` if it is an integer ``>= minimum``; else a ``ValueError``.

    >>> require_int("model.hidden", 32.9)
    Traceback (most recent call last):
    ...
    ValueError: model.hidden must be an integer, got 32.9 (float)
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{key} must be an integer, got {_kind(value)}")
    if value < minimum:
        what = {0: "a non-negative integer", 1: "a positive integer"}.get(
            minimum, f"an integer >= {minimum}"
        )
        raise ValueError(f"{key} must be {what}, got {value}")
    return int(value)


def require_switch(key: str, value: Any) -> int:
    """``value`` as 0 or 1 if it is a boolean or the integer 0 or 1; else a ``ValueError``."""
    if isinstance(value, numbers.Integral) and value in (0, 1):
        return int(value)
    raise ValueError(f"{key} must be 0 or 1 (false/true), got {_kind(value)}")


def require_nonnegative(key: str, value: Any) -> float:
    """``value`` as a ``float`` if it is a finite real number ``>= 0``; else a ``ValueError``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{key} must be a finite number >= 0, got {_kind(value)}")
    number = float(value)
    if not (math.isfinite(number) and number >= 0.0):
        raise ValueError(f"{key} must be a finite number >= 0, got {_kind(value)}")
    return number
