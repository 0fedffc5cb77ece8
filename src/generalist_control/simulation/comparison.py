"""Closed-loop scores of any batch controller against the LQI experts, on steps from rest."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from generalist_control.plants.definition import Plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.scenarios import references
from generalist_control.simulation.simulate import (
    BatchController,
    PerPlantController,
    Run,
    Trajectory,
    simulate_many,
)

__all__ = ["ClosedLoopScore", "output_mse"]


def output_mse(
    controller: BatchController, plants: Sequence[Plant], duration: float = 15.0
) -> dict[str, float]:
    """Per plant, mean ``(y - y_LQI)**2`` on a scaled unit step from rest (inf: diverged)."""
    spec = {"kind": "step", "amplitude": 1.0, "duration": float(duration)}
    runs = [Run(p, *references("step", spec, p), None) for p in plants]
    ours = simulate_many(runs, controller)
    lqi = simulate_many(runs, PerPlantController(LQIController))
    return {
        p.name: float("inf") if a.diverged.any() else float(np.mean((a.y - b.y) ** 2))
        for p, a, b in zip(plants, ours, lqi, strict=True)
    }


class ClosedLoopScore:
    """Per plant, a controller's output error against LQI on steps, relative to LQI's, capped at 1.

    ``mean((y - y_LQI)**2) / mean(y_LQI**2)`` over steps of each amplitude (times the
    plant's ``amplitude_scale``) from rest, 1 for a diverged run; LQI is simulated once, on
    the first call. Keyed by ``labels`` (one per plant, distinct: variants share their plant's
    name), else by the plants' names.

    Raises
    ------
    ValueError
        ``labels`` does not name each plant once.
    """

    def __init__(
        self,
        plants: Sequence[Plant],
        amplitudes: Sequence[float] = (1.0, -3.0),
        duration: float = 10.0,
        labels: Sequence[str] | None = None,
    ) -> None:
        self.keys = [p.name for p in plants] if labels is None else list(labels)
        if len(self.keys) != len(plants) or len(set(self.keys)) != len(self.keys):
            raise ValueError(
                f"ClosedLoopScore needs one distinct label per plant, got {len(self.keys)} "
                f"labels ({len(set(self.keys))} distinct) for {len(plants)} plants"
            )
        steps = int(round(duration / plants[0].dt)) if plants else 0
        amps = np.asarray(amplitudes, dtype=float)
        self.runs = [Run(p, np.repeat(amps[:, None] * p.amplitude_scale, steps, axis=1))
                     for p in plants]  # fmt: skip
        self._lqi: list[Trajectory] | None = None

    def __call__(self, controller: BatchController) -> dict[str, float]:
        """Per plant (or label), ``controller``'s score."""
        ours = simulate_many(self.runs, controller)
        if self._lqi is None:
            self._lqi = simulate_many(self.runs, PerPlantController(LQIController))
        out = {}
        for key, a, b in zip(self.keys, ours, self._lqi, strict=True):
            if a.diverged.any():
                out[key] = 1.0
                continue
            err = np.mean((a.y - b.y) ** 2, axis=1) / np.maximum(np.mean(b.y**2, axis=1), 1e-300)
            out[key] = float(min(1.0, err.mean()))
        return out
