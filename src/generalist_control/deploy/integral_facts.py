"""What an integrating policy's runtime needs of each plant beyond the policy itself.

Its output row ``C`` and which way its integral moves the command (anti-windup): the
policy's meta, else the catalogue.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.lqi import design_lqi

__all__ = ["IntegralFacts", "integral_facts"]


def integral_facts(names: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Per catalogue plant in ``names``, its ``outputs`` row ``C`` and ``integral_directions``.

    The sign of its expert's ``-Ki``, as the policy's meta stores them; unknown names left out.
    """
    known = set(available_plants())
    plants = [load_plant(n) for n in sorted(names) if n in known]
    return {
        "outputs": {p.name: [float(c) for c in p.C[0]] for p in plants},
        "integral_directions": {p.name: float(np.sign(-design_lqi(p).Ki)) for p in plants},
    }


class IntegralFacts:
    """Output rows and integral directions per plant: the policy's meta, else the catalogue."""

    def __init__(self, meta: Mapping[str, Any]) -> None:
        outputs, directions = meta.get("outputs", {}), meta.get("integral_directions", {})
        self.outputs = {str(k): np.asarray(v, np.float64) for k, v in outputs.items()}
        self.directions = {str(k): float(v) for k, v in directions.items()}
        self._unknown: set[str] = set()  # plants neither the meta nor the catalogue knows

    def add(self, plant: Plant) -> None:
        """Take ``plant``'s output row and its expert's integral direction (a plant given)."""
        self.outputs[plant.name] = np.asarray(plant.C[0], np.float64)
        self.directions[plant.name] = float(np.sign(-design_lqi(plant).Ki))

    def _complete(self, names: Sequence[str]) -> None:
        missing = sorted(set(names) - (set(self.outputs) & set(self.directions)) - self._unknown)
        if missing:
            facts = integral_facts(missing)
            for k, v in facts["outputs"].items():
                self.outputs.setdefault(k, np.asarray(v, np.float64))
            for k, v in facts["integral_directions"].items():
                self.directions.setdefault(k, v)
            self._unknown.update(set(missing) - set(facts["outputs"]))

    def output_rows(self, names: Sequence[str]) -> np.ndarray:
        """``C`` (B, MAX_ORDER) of plants ``names``, zero-padded.

        Raises
        ------
        ValueError
            If a plant's row is known to neither; the fix: pass the measured output.
        """
        self._complete(names)
        missing = sorted({s for s in names if s not in self.outputs})
        if missing:
            raise ValueError(
                f"this policy integrates the tracking error but has no output map for "
                f"{', '.join(missing)}: pass the measured output, step(x, r, y)"
            )
        C = np.zeros((len(names), MAX_ORDER))
        for i, name in enumerate(names):
            C[i, : len(self.outputs[name])] = self.outputs[name]
        return C

    def directions_of(self, names: Sequence[str]) -> np.ndarray:
        """Per plant of ``names``, the direction of its integral action (anti-windup).

        Raises
        ------
        ValueError
            If a plant's direction is known to neither.
        """
        self._complete(names)
        unknown = sorted(set(names) - set(self.directions))
        if unknown:
            raise ValueError(
                f"anti-windup needs the direction of each plant's integral action; none "
                f"for {', '.join(unknown)} (not in the policy's meta nor the catalogue)"
            )
        return np.array([self.directions[n] for n in names])
