"""Plants a runtime is given by their model (the model card route), not by name."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from generalist_control.model.bank import NoModelRowError, add_plant
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import Plant
from generalist_control.plants.given import plant_from_file, plant_from_model

__all__ = ["GIVEN_TYPES", "GivenPlant", "grown_for", "plant_of", "refused_reset", "unknown_plant"]

#: What ``reset`` takes as one plant: a name, a plant YAML's path, a model dict, a Plant.
GivenPlant = str | Path | Mapping[str, Any] | Plant
#: The same, for ``isinstance``.
GIVEN_TYPES = (str, Path, Mapping, Plant)


def plant_of(item: GivenPlant) -> Plant | str:
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
