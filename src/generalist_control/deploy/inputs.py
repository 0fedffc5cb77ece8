"""What the runtime takes as a number: real values, and positive actuator limits.

NumPy casts a complex array to float by dropping its imaginary part (with a warning at
most); the runtime refuses complex inputs instead (:func:`real_array`), as it refuses NaN.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from generalist_control.plants.plant import MAX_ORDER

__all__ = ["actuator_limit", "real_array", "shaped_inputs"]


def real_array(value: Any, name: str) -> np.ndarray:
    """``value`` as a float64 array; a complex one is refused.

    Raises
    ------
    TypeError
        If ``value`` is complex (its imaginary part would be dropped), naming ``name``.
    """
    a = np.asarray(value)
    if a.dtype.kind == "c":
        raise TypeError(
            f"{name} is complex ({a.dtype}); the runtime takes real values only. Pass the "
            f"real part (e.g. np.real(...)) if the imaginary part is meant to be zero."
        )
    return a if a.dtype == np.float64 else a.astype(np.float64)


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


def shaped_inputs(
    x: Any, r: Any, systems: Sequence[str], order: np.ndarray, single: bool
) -> tuple[np.ndarray, np.ndarray]:
    """A step's state and reference as float64 arrays (B, n) and (B,), their shapes checked.

    ``single``: one plant, ``x`` of its order ``n`` and a scalar ``r``; otherwise a batch of
    ``len(systems)`` zero-padded states (B, MAX_ORDER) or (B, highest order) and ``r`` (B,).

    Raises
    ------
    ValueError
        If a shape is not that.
    TypeError
        If ``x`` or ``r`` is complex (:func:`real_array`).
    """
    x, r = real_array(x, "state x"), real_array(r, "reference r")
    if single:
        n = int(order[0])
        if x.shape != (n,):
            raise ValueError(f"state has shape {x.shape}; plant '{systems[0]}' has {n} states")
        if r.size != 1:
            raise ValueError(f"reference has shape {r.shape}; expected a scalar")
        return x[None, :], r.reshape(1)
    B = len(systems)
    if x.ndim != 2 or x.shape[0] != B or x.shape[1] not in (MAX_ORDER, order.max()):
        raise ValueError(
            f"state batch has shape {x.shape}; expected ({B}, {MAX_ORDER}) zero-padded"
        )
    if r.shape != (B,):
        raise ValueError(f"reference batch has shape {r.shape}; expected ({B},)")
    return x, r
