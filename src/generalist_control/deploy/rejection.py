"""The runtime's refusal of a step: :class:`RejectedStep` and its message.

:class:`~generalist_control.deploy.runtime.PolicyRuntime` refuses a step whose inputs,
error integral or controls leave the policy's range; :func:`rejection` words the error:
which rows and plants, which input, its value, the allowed range and what to do.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

__all__ = ["RejectedStep", "rejection"]

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

    ``kind`` names the input (``state``, ``reference``, ``output``, ``error integral``,
    ``network output``), ``limit`` its allowed magnitudes, ``systems`` and ``order`` the
    rows' plants, ``single`` whether the runtime steps one plant (rows go unnamed) and
    ``input_limit`` how many training RMS a signal may reach.
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
