"""Strict value checks for settings that parts read themselves (the network's parts).

A part built from config (``conf/model``) checks its own arguments with these, naming the
config key: a float, even ``32.0``, is never a size; a boolean is not a size either. The
training's other sections are read by :mod:`generalist_control.common.settings`.
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

    Python and NumPy integers pass; floats (even ``32.0``), booleans and strings do not.

    Examples
    --------
    >>> require_int("model.hidden", 32)
    32
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


def require_nonnegative(key: str, value: Any, what: str = "number") -> float:
    """``value`` as a ``float`` if it is a finite real number ``>= 0``; else a ``ValueError``.

    ``what`` names the quantity in the message (``"a finite fraction >= 0"``).

    Examples
    --------
    >>> require_nonnegative("dagger.noise", 0.05, "fraction")
    0.05
    >>> require_nonnegative("dagger.noise", -1, "fraction")
    Traceback (most recent call last):
    ...
    ValueError: dagger.noise must be a finite fraction >= 0, got -1 (int)
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{key} must be a finite {what} >= 0, got {_kind(value)}")
    number = float(value)
    if not (math.isfinite(number) and number >= 0.0):
        raise ValueError(f"{key} must be a finite {what} >= 0, got {_kind(value)}")
    return number
