"""Adapters: the policy runtime as the simulator's controllers.

:class:`RuntimeAdapter` drives a :class:`~generalist_control.deploy.runtime.PolicyRuntime`
as a batch controller (:func:`~generalist_control.simulation.simulate.simulate_many`);
:class:`SinglePlantAdapter` as a single-plant controller (e.g. the Crazyflie loop).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.plants.plant import MAX_ORDER
from generalist_control.simulation.simulate import Perturbation, row_slices

__all__ = ["RuntimeAdapter", "SinglePlantAdapter", "stacked_output"]


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


class RuntimeAdapter:
    """Adapter: a :class:`PolicyRuntime` as the simulator's batch controller.

    Parameters
    ----------
    runtime : PolicyRuntime
    limits : Perturbation, optional
        Actuator limits the runtime's anti-windup knows (see
        :meth:`PolicyRuntime.set_actuator_limits`); None: it knows none.
    """

    def __init__(self, runtime: PolicyRuntime, limits: Perturbation | None = None) -> None:
        self.runtime, self.limits = runtime, limits
        self._output: Callable[[np.ndarray], np.ndarray] | None = None

    def reset(self, plants: Sequence[Any], counts: Sequence[int]) -> None:
        """One batch row per run, plant names repeated by their counts."""
        lim = self.limits or Perturbation()
        self.runtime.set_actuator_limits(lim.u_limit, lim.rate_limit)
        self.runtime.reset([p.name for p, c in zip(plants, counts, strict=True) for _ in range(c)])
        self._output = stacked_output(plants, counts) if self.runtime.integral else None

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls for zero-padded states (and their plants' outputs, if integrating)."""
        if self._output is None:
            return self.runtime.step(x, r)
        return self.runtime.step(x, r, self._output(x))


class SinglePlantAdapter:
    """The runtime as a single-plant controller (unpadded states of one plant)."""

    def __init__(self, runtime: PolicyRuntime, plant: str) -> None:
        self.runtime, self.plant = runtime, plant

    def reset(self, batch_size: int) -> None:
        """One runtime row per run."""
        self.runtime.reset([self.plant] * batch_size)

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls for unpadded states."""
        padded = np.zeros((x.shape[0], MAX_ORDER))
        padded[:, : x.shape[1]] = x
        return self.runtime.step(padded, r)  # an integrating policy: y = C x (its meta)
