"""What the runtime refuses, and how it says so.

Inputs are real numbers of the expected shapes (NumPy would turn a complex value, a string
or a bool into a float without a word); a step out of range is a :class:`RejectedStep`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from generalist_control.plants.definition import MAX_ORDER

__all__ = ["RejectedStep", "actuator_limit", "real_array", "rejection", "shaped_inputs"]

_ADVICE = {
    "input": "Check the measurement, its units and that it is a deviation from the operating "
    "point; a plant really this far out is beyond the policy's training: hand over to a "
    "fallback controller and reset().",
    "error integral": "The error integral would wind up beyond its range: declare actuator "
    "limits (set_actuator_limits) for anti-windup, check the measured output, or reset().",
    "network output": "The policy's command is unusable (a corrupt policy file, e.g. NaN "
    "weights, or inputs unlike its training data): hand over to a fallback controller.",
}
_LABELS = {
    "state": "state entry {}",
    "reference": "reference r",
    "output": "measured output y",
    "error integral": "error integral z after this sample",
    "network output": "control u[k+{}]",
}


class RejectedStep(ValueError):
    """A step the runtime refused, its state unchanged; ``rows``: the batch rows at fault."""

    def __init__(self, message: str, rows: Iterable[int]) -> None:
        super().__init__(message)
        self.rows = tuple(int(i) for i in rows)


def rejection(
    kind: str,
    values: np.ndarray,
    limit: np.ndarray,
    ok: np.ndarray,
    systems: Sequence[str],
    order: np.ndarray,
    single: bool,
    input_limit: float,
) -> RejectedStep:
    """The error for the entries of ``values`` (B,) or (B, n) that are not ``ok``.

    ``kind``: a key of ``_LABELS``; ``single``: one plant (rows go unnamed).
    """
    B = len(values)
    v, lim = values.reshape(B, -1), np.broadcast_to(limit, values.shape).reshape(B, -1)
    bad_rows = np.flatnonzero(~ok.reshape(B, -1).all(axis=1))
    items = []
    for i in bad_rows[:4]:
        j = int(np.flatnonzero(~ok.reshape(B, -1)[i])[0])
        label = _LABELS[kind].format(j)
        if kind == "state" and j >= order[i]:
            label += f" (padding beyond the plant's order {order[i]}: keep it zero)"
        where = f"plant '{systems[i]}'"
        where = where if single else f"row {i} ({where})"
        if np.isfinite(v[i, j]):
            problem = (
                f"is outside the allowed range |value| <= {lim[i, j]:.4g} "
                f"(= {input_limit:g} x the training RMS {lim[i, j] / input_limit:.4g})"
            )
        else:
            problem = f"is not finite ({kind} contains NaN or inf)"
        items.append(f"{where}: {label} = {v[i, j]:.6g} {problem}")
    more = f" (and {len(bad_rows) - 4} more rows)" if len(bad_rows) > 4 else ""
    text = f"{'; '.join(items)}{more}. {_ADVICE.get(kind, _ADVICE['input'])}"
    return RejectedStep(f"step refused, the runtime's state is unchanged: {text}", bad_rows)


def real_array(value: Any, name: str) -> np.ndarray:
    """``value`` as a float64 array; anything but real numbers is refused.

    Raises
    ------
    TypeError
        If ``value`` is complex (its imaginary part would be dropped), a bool, a string or
        anything else that is not a real number, naming ``name``.
    """
    a = np.asarray(value)
    kind = a.dtype.kind
    if kind in "fiu":
        return a if a.dtype == np.float64 else a.astype(np.float64)
    if kind == "c":
        raise TypeError(
            f"{name} is complex ({a.dtype}); the runtime takes real values only. Pass the "
            f"real part (e.g. np.real(...)) if the imaginary part is meant to be zero."
        )
    what = {"b": "a bool", "U": "a string", "S": "bytes"}.get(kind, f"of type {a.dtype}")
    raise TypeError(
        f"{name} is {what} ({value!r:.60}); the runtime takes real numbers only (int or "
        f"float, or arrays of them). Convert it first, e.g. float(...) for a number read "
        f"as text, in the plant's units."
    )


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

    ``single``: ``x`` of the plant's order and a scalar ``r``; else zero-padded states (B,
    MAX_ORDER) or (B, highest order) and ``r`` (B,).

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
