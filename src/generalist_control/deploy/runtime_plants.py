"""The plants a runtime steps beyond the policy's own: given by their model, and their facts.

A plant given at ``reset`` (a plant YAML, a model dict) gets a row computed from its model; an
integrating policy needs each plant's output row ``C`` and which way its integral moves the
command (anti-windup): the policy's meta, else the catalogue.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from generalist_control.model.bank import NoModelRowError, add_plant
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.plants.config import plant_from_file, plant_from_model
from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.lqi import design_lqi

__all__ = [
    "GIVEN_TYPES",
    "IntegralFacts",
    "grown_for",
    "integral_facts",
    "plant_of",
    "refused_reset",
    "unknown_plant",
]

#: What ``reset`` takes as one plant: a name, a plant YAML's path, a model dict, a Plant.
GIVEN_TYPES = (str, Path, Mapping, Plant)


def plant_of(item: str | Path | Mapping[str, Any] | Plant) -> Plant | str:
    """The plant a ``reset`` item gives by its model, or the name it gives."""
    if isinstance(item, Plant):
        return item
    if isinstance(item, Mapping):
        return plant_from_model(item)
    if isinstance(item, Path) or str(item).endswith((".yaml", ".yml")):
        return plant_from_file(item)
    return str(item)


def grown_for(policy: Policy, plant: Plant, dt: float) -> Policy:
    """``policy`` grown by ``plant``'s row, computed from its model.

    Raises
    ------
    ValueError
        If the plant's sample time is not the policy's, the policy cannot take a plant from
        its model (the tag route learns its rows: train a card policy or learn a row with
        ``python adapt.py``; in context it reads the plant from the window with its data's
        scales), or the card is refused (its message says why).
    """
    if abs(plant.dt - dt) > 1e-12 * dt:
        raise ValueError(
            f"plant '{plant.name}' is sampled at dt = {plant.dt} s, the policy at {dt} s: "
            "resample the model (or train a policy at its dt)"
        )
    try:
        return add_plant(policy, plant)
    except NoModelRowError as exc:
        raise ValueError(
            f"plant '{plant.name}' is not one of the plants this policy was trained on, and "
            f"its plant part ({exc}) cannot take a plant from its model: use a policy of the "
            "model card route (python train.py experiment=family_card), or learn the plant's "
            f"row: python adapt.py plant=<its YAML>"
        ) from None


def refused_reset(system: Any, known: list[str]) -> Exception:
    """The error for a ``reset`` argument that is neither a plant nor a list of them."""
    if isinstance(system, list | tuple) and not system:
        return ValueError(f"reset needs at least one plant; known: {', '.join(known)}")
    return TypeError(
        f"reset takes a plant (a name, a plant YAML's path, a model dict) or a list of them, "
        f"e.g. reset('cstr') or reset(['cstr', 'cstr']); got {system!r:.80} "
        f"({type(system).__name__}). This policy knows: {', '.join(known)}"
    )


def unknown_plant(name: str, known: list[str]) -> KeyError:
    """The error for a name the policy does not know, saying how to give a new plant."""
    return KeyError(
        f"unknown plant '{name}' for this policy; it was trained on: {', '.join(known)}. A "
        "plant it never saw is given by its model: reset('<plant>.yaml') or reset({'A': ..., "
        "'B': ..., 'C': ..., 'dt': ..., 'Q': ..., 'R': ...}) (the model card route)"
    )


def integral_facts(
    names: Iterable[str] = (), plants: Iterable[Plant] = ()
) -> dict[str, dict[str, Any]]:
    """The meta's ``outputs`` (row ``C``) and ``integral_directions`` (sign of LQI's ``-Ki``).

    Of the catalogue plants in ``names`` (sorted; unknown names left out), then of ``plants``.
    """
    names = sorted(names)
    known = set(available_plants()) if names else set()
    every = [*(load_plant(n) for n in names if n in known), *plants]
    return {
        "outputs": {p.name: [float(c) for c in p.C[0]] for p in every},
        "integral_directions": {p.name: float(np.sign(-design_lqi(p).Ki)) for p in every},
    }


class IntegralFacts:
    """Output rows and integral directions per plant: the policy's meta, else the catalogue."""

    def __init__(self, meta: Mapping[str, Any]) -> None:
        self.outputs: dict[str, np.ndarray] = {}
        self.directions: dict[str, float] = {}
        self._take(meta, replace=True)
        self._unknown: set[str] = set()  # plants neither the meta nor the catalogue knows

    def _take(self, facts: Mapping[str, Any], replace: bool) -> None:
        """Take the rows and directions of ``facts`` (as :func:`integral_facts` gives them)."""
        for k, v in facts.get("outputs", {}).items():
            if replace or str(k) not in self.outputs:
                self.outputs[str(k)] = np.asarray(v, np.float64)
        for k, v in facts.get("integral_directions", {}).items():
            if replace or str(k) not in self.directions:
                self.directions[str(k)] = float(v)

    def add(self, plant: Plant) -> None:
        """Take ``plant``'s output row and its expert's integral direction (a plant given)."""
        self._take(integral_facts(plants=[plant]), replace=True)

    def _complete(self, names: Sequence[str]) -> None:
        missing = sorted(set(names) - (set(self.outputs) & set(self.directions)) - self._unknown)
        if missing:
            facts = integral_facts(missing)
            self._take(facts, replace=False)
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
