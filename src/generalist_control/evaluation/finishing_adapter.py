"""The policy runtime as a controller of runs that end at different samples.

:class:`FinishingAdapter` drives a :class:`~generalist_control.deploy.runtime.PolicyRuntime`
in :func:`~generalist_control.simulation.stacked.simulate_stacked`, like
:class:`~generalist_control.deploy.adapter.RuntimeAdapter` in ``simulate_many``: the same
calls (:func:`~generalist_control.deploy.adapter.step_live`,
:func:`~generalist_control.deploy.adapter.stacked_output`), so the same controls. In addition
it drops the rows of a run that has ended from the runtime (the network's cost is per row)
and keeps each row's error integral as it stood at the run's end.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from generalist_control.deploy.adapter import stacked_output, step_live
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.simulation.simulate import Perturbation

__all__ = ["FinishingAdapter"]


class FinishingAdapter:
    """A :class:`PolicyRuntime` as a batch controller whose runs may end early.

    Parameters
    ----------
    runtime : PolicyRuntime
    limits : Perturbation, optional
        Actuator limits the runtime's anti-windup knows; None: none.

    Attributes
    ----------
    refused : dict
        Per row the runtime refused (commanded NaN from then on), its message.
    z_end : ndarray
        Per row, the runtime's error integral after the run's last sample (NaN: refused,
        not ended yet, or no ``integral`` channel).
    """

    def __init__(self, runtime: PolicyRuntime, limits: Perturbation | None = None) -> None:
        self.runtime, self.limits = runtime, limits
        self._output: Callable[[np.ndarray], np.ndarray] | None = None
        self._rows = np.zeros(0, np.int64)  # the batch rows the runtime holds, in its order
        self.refused: dict[int, str] = {}
        self.z_end = np.zeros(0)

    def reset(self, plants: Sequence[Any], counts: Sequence[int]) -> None:
        """One runtime row per run, plant names repeated by their counts."""
        lim = self.limits or Perturbation()
        self.runtime.set_actuator_limits(lim.u_limit, lim.rate_limit)
        self.runtime.reset([p.name for p, c in zip(plants, counts, strict=True) for _ in range(c)])
        self._output = stacked_output(plants, counts) if self.runtime.integral else None
        self._rows = np.arange(sum(counts), dtype=np.int64)
        self.refused, self.z_end = {}, np.full(sum(counts), np.nan)

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls (B,) for zero-padded states: NaN for the rows refused or ended."""
        u = np.full(x.shape[0], np.nan)
        rows = self._rows
        if not rows.size:
            return u
        y = None if self._output is None else self._output(x)[rows]
        live, refused = np.ones(rows.size, bool), dict[int, str]()
        u[rows] = step_live(self.runtime, live, x[rows], r[rows], y, refused)
        self.refused.update({int(rows[i]): msg for i, msg in refused.items()})
        self._rows = rows[live]
        return u

    def finish(self, rows: np.ndarray) -> None:
        """The runs of ``rows`` ended: keep their error integrals, drop them from the runtime."""
        gone = np.isin(self._rows, rows)
        if not gone.any():
            return
        if self.runtime.integral:
            self.z_end[self._rows[gone]] = self.runtime.z[gone]
        if not gone.all():
            self.runtime.select(np.flatnonzero(~gone))
        self._rows = self._rows[~gone]
