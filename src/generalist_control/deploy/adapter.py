"""Adapters: the policy runtime as the simulator's controllers.

:class:`RuntimeAdapter` drives a :class:`~generalist_control.deploy.runtime.PolicyRuntime`
as a batch controller (:func:`~generalist_control.simulation.simulate.simulate_many`);
:class:`SinglePlantAdapter` as a single-plant controller (e.g. the Crazyflie loop).

The runtime refuses a step whose inputs, error integral or controls leave the policy's range
(:class:`~generalist_control.deploy.runtime.RejectedStep`). In a simulated loop that means the
run has diverged as far as the policy is concerned: both adapters drop such a run from the
runtime for the rest of the loop (:func:`step_live`) and command NaN for it, which the
simulators record as diverged, while the other runs go on unchanged.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from generalist_control.deploy.runtime import PolicyRuntime, RejectedStep
from generalist_control.plants.definition import MAX_ORDER
from generalist_control.simulation.simulate import Perturbation, row_slices

__all__ = ["RuntimeAdapter", "SinglePlantAdapter", "stacked_output", "step_live"]


def stacked_output(
    plants: Sequence[Any], counts: Sequence[int]
) -> Callable[[np.ndarray], np.ndarray]:
    """``y(x)`` for zero-padded states of ``counts[i]`` stacked runs of ``plants[i]``.

    Each group of rows goes through its plant's own output map (``plant.output``, nonlinear
    where the plant's is), as the LQI expert measures it.
    """
    parts = list(zip(plants, row_slices(counts), strict=True))

    def output(x: np.ndarray) -> np.ndarray:
        y = np.empty(x.shape[0])
        for plant, rows in parts:
            y[rows] = plant.output(np.asarray(x[rows, : plant.order], dtype=np.float64))
        return y

    return output


def step_live(
    runtime: PolicyRuntime,
    live: np.ndarray,
    x: np.ndarray,
    r: np.ndarray,
    y: np.ndarray | None = None,
    refused: dict[int, str] | None = None,
) -> np.ndarray:
    """Controls (B,) for the rows still ``live`` (bool (B,), updated in place), NaN elsewhere.

    ``runtime`` holds exactly the live rows of a batch reset, in order. A row it refuses
    (:class:`RejectedStep`) is marked not live, dropped from the runtime
    (:meth:`PolicyRuntime.select`) and the step made again without it, which is the same
    step for the others: a refused step changes nothing. ``refused`` collects, per row,
    the runtime's message.
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
    """Adapter: a :class:`PolicyRuntime` as the simulator's batch controller.

    Parameters
    ----------
    runtime : PolicyRuntime
    limits : Perturbation, optional
        Actuator limits the runtime's anti-windup knows (see
        :meth:`PolicyRuntime.set_actuator_limits`); None: it knows none.

    Attributes
    ----------
    refused : dict
        Per row of the current run that the runtime refused (commanded NaN from then on,
        see :func:`step_live`), the runtime's message.
    """

    def __init__(self, runtime: PolicyRuntime, limits: Perturbation | None = None) -> None:
        self.runtime, self.limits = runtime, limits
        self._output: Callable[[np.ndarray], np.ndarray] | None = None
        self._live = np.zeros(0, bool)
        self.refused: dict[int, str] = {}

    def reset(self, plants: Sequence[Any], counts: Sequence[int]) -> None:
        """One batch row per run, plant names repeated by their counts."""
        lim = self.limits or Perturbation()
        self.runtime.set_actuator_limits(lim.u_limit, lim.rate_limit)
        self.runtime.reset([p.name for p, c in zip(plants, counts, strict=True) for _ in range(c)])
        self._output = stacked_output(plants, counts) if self.runtime.integral else None
        self._live, self.refused = np.ones(sum(counts), bool), {}

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls for zero-padded states (and their plants' outputs, if integrating)."""
        y = None if self._output is None else self._output(x)
        return step_live(self.runtime, self._live, x, r, y, self.refused)

    def record_applied(self, u: np.ndarray) -> None:
        """Record the controls (B,) the plants received instead of the last step's.

        See :meth:`PolicyRuntime.record_applied`; rows the runtime refused are skipped.
        """
        if self._live.any():
            self.runtime.record_applied(np.asarray(u, dtype=np.float64)[self._live])


class SinglePlantAdapter:
    """The runtime as a single-plant controller (unpadded states of one plant).

    Runs the runtime refuses are commanded NaN from then on (:func:`step_live`); the
    runtime's messages are in :attr:`refused` (per run).
    """

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
