"""The policy runtime as the simulators' batch and single-plant controllers.

A run the runtime refuses has diverged as far as the policy is concerned: it leaves the
runtime and is commanded NaN (recorded as diverged), while the other runs go on unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from generalist_control.deploy.runtime import PolicyRuntime, RejectedStep
from generalist_control.plants.definition import MAX_ORDER
from generalist_control.simulation.perturbation import Perturbation
from generalist_control.simulation.simulate import row_slices

__all__ = ["RuntimeAdapter", "SinglePlantAdapter", "step_live"]


def step_live(
    runtime: PolicyRuntime,
    live: np.ndarray,
    x: np.ndarray,
    r: np.ndarray,
    y: np.ndarray | None = None,
    refused: dict[int, str] | None = None,
) -> np.ndarray:
    """Controls (B,) for the rows still ``live`` (bool (B,), updated in place), NaN elsewhere.

    ``runtime`` holds exactly the live rows, in order. A row it refuses is marked not live,
    dropped from the runtime and the step made again without it (a refused step changes
    nothing); ``refused`` collects, per row, the runtime's message.
    """
    u = np.full(live.shape, np.nan)
    while live.any():
        idx = np.flatnonzero(live)
        sel = slice(None) if idx.size == live.size else idx
        try:
            if y is None:
                u[sel] = runtime.step(x[sel], r[sel])
            else:
                u[sel] = runtime.step(x[sel], r[sel], y[sel])
            return u
        except RejectedStep as err:
            lost = idx[list(err.rows)]
            live[lost] = False
            if refused is not None:
                refused.update({int(i): str(err) for i in lost})
            keep = np.flatnonzero(live[idx])
            if keep.size:
                runtime.select(keep)
    return u


class RuntimeAdapter:
    """A :class:`PolicyRuntime` as the simulators' batch controller.

    Rows the runtime refuses are commanded NaN from then on (:func:`step_live`), their
    messages in :attr:`refused`. In ``simulate_stacked`` the rows of an ended run leave the
    runtime (:meth:`finish`), and :attr:`z_end` keeps each row's error integral at its run's
    end (NaN: refused, not ended yet, or no ``integral`` channel).

    Parameters
    ----------
    runtime : PolicyRuntime
    limits : Perturbation, optional
        Actuator limits the runtime's anti-windup knows; None: none.
    """

    def __init__(self, runtime: PolicyRuntime, limits: Perturbation | None = None) -> None:
        self.runtime, self.limits = runtime, limits
        self._parts: list[tuple[Any, slice]] = []  # each plant's rows (integrating policy)
        self._rows = np.zeros(0, np.int64)  # the batch rows the runtime holds, in its order
        self.refused: dict[int, str] = {}
        self.z_end = np.zeros(0)

    def reset(self, plants: Sequence[Any], counts: Sequence[int]) -> None:
        """One batch row per run, plant names repeated by their counts."""
        lim = self.limits or Perturbation()
        self.runtime.set_actuator_limits(lim.u_limit, lim.rate_limit)
        self.runtime.reset([p.name for p, c in zip(plants, counts, strict=True) for _ in range(c)])
        parts = list(zip(plants, row_slices(counts), strict=True))
        self._parts = parts if self.runtime.integral else []
        self._rows = np.arange(sum(counts), dtype=np.int64)
        self.refused, self.z_end = {}, np.full(sum(counts), np.nan)

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls (B,) for zero-padded states: NaN for the rows refused or ended."""
        u = np.full(x.shape[0], np.nan)
        rows = self._rows
        if not rows.size:
            return u
        y = self._outputs(x)[rows] if self._parts else None
        live, refused = np.ones(rows.size, bool), dict[int, str]()
        u[rows] = step_live(self.runtime, live, x[rows], r[rows], y, refused)
        self.refused.update({int(rows[i]): msg for i, msg in refused.items()})
        self._rows = rows[live]
        return u

    def _outputs(self, x: np.ndarray) -> np.ndarray:
        """``y(x)``: each plant's rows through its own output map, as the LQI expert measures."""
        y = np.empty(x.shape[0])
        for plant, rows in self._parts:
            y[rows] = plant.output(np.asarray(x[rows, : plant.order], dtype=np.float64))
        return y

    def record_applied(self, u: np.ndarray) -> None:
        """Record the controls (B,) the plants received (:meth:`PolicyRuntime.record_applied`)."""
        if self._rows.size:
            self.runtime.record_applied(np.asarray(u, dtype=np.float64)[self._rows])

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


class SinglePlantAdapter:
    """The runtime as a single-plant controller (unpadded states); refusals as above."""

    def __init__(self, runtime: PolicyRuntime, plant: str) -> None:
        self.runtime, self.plant = runtime, plant
        self._live = np.zeros(0, bool)
        self.refused: dict[int, str] = {}

    def reset(self, batch_size: int) -> None:
        """One runtime row per run."""
        self.runtime.reset([self.plant] * batch_size)
        self._live, self.refused = np.ones(batch_size, bool), {}

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls for unpadded states."""
        padded = np.zeros((x.shape[0], MAX_ORDER))
        padded[:, : x.shape[1]] = x
        r = np.asarray(r, dtype=np.float64).reshape(-1)
        return step_live(self.runtime, self._live, padded, r, None, self.refused)  # y = C x
