"""What the runtime takes as a number: positive actuator limits."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["actuator_limit"]


def actuator_limit(value: Any, name: str) -> float | None:
    """A known actuator limit: None (no limit) or a positive number (``inf``: no limit).

    Raises
    ------
    ValueError
        If ``value`` is not a number > 0 (zero, negative or NaN), naming ``name``.
    """
    if value is None:
        return None
    try:
        limit = float(value)
    except (TypeError, ValueError):
        limit = math.nan
    if not limit > 0:
        raise ValueError(
            f"{name} must be a positive number (or None for no limit); got {value!r}. A limit "
            f"of zero or below, or NaN, would freeze the error integral or make the command "
            f"NaN: pass the actuator's real limit, in the plant's control units (per second "
            f"for rate_limit)."
        )
    return limit
