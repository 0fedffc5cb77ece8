"""Plants no training saw, met zero-shot: ``val/closed_loop`` scores new members of a family.

Scored on its training plants alone, the closed-loop check keeps the checkpoint that best
controls what it was fitted on; a family route is meant for plants it never saw, so its
checkpoint is chosen on those too (docs/notes/family-policy.md, experiment 13).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from generalist_control.deploy.runtime_plants import integral_facts
from generalist_control.model.bank import add_plants
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import Plant
from generalist_control.simulation.family_draw import draw_family, read_families

__all__ = ["UnseenDraw"]


@dataclass(frozen=True)
class UnseenDraw:
    """A family draw a policy meets as it would at deployment: rows from the plants' models."""

    plants: tuple[Plant, ...]

    @classmethod
    def draw(cls, family: Mapping[str, Any], policy: Policy) -> UnseenDraw:
        """``family`` (a ``conf/families`` group, plain types) drawn and met (:meth:`of`).

        Raises
        ------
        ValueError
            Naming the key: a family the generator refuses, too few plants that pass, or a
            plant part that computes no row from a plant's model.
        """
        generator, settings = read_families(family)
        plants = draw_family(generator, settings.count, settings.checks).plants
        return cls.of(plants, policy)

    @classmethod
    def of(cls, plants: Sequence[Plant], policy: Policy) -> UnseenDraw:
        """``plants`` (tags ``0 .. k-1``: their places) as ``policy``'s plant part meets them.

        Raises
        ------
        ValueError
            If the plant part computes no row from a plant's model (only the card does).
        """
        plants = tuple(plants)
        if policy.net.plant.plant_rows(list(plants[:1]), policy.width) is None:
            raise ValueError(
                f"this policy (model.plant: {type(policy.net.plant).__name__}) cannot meet "
                "zero-shot a plant no training saw: train it with model/plant=card (or set "
                "train_families.validation=null)"
            )
        return cls(plants)

    def met(self, policy: Policy, meta: Mapping[str, Any]) -> tuple[Policy, dict[str, Any]]:
        """``policy`` grown by the draw's rows, and its meta naming the draw's plants."""
        grown = add_plants(policy, self.plants)
        first, plants = policy.net.n_tags, self.plants
        facts = integral_facts(plants=plants)
        return grown, {
            **meta,
            "tags": {**meta["tags"], **{p.name: first + i for i, p in enumerate(plants)}},
            "orders": {**meta["orders"], **{p.name: p.order for p in plants}},
            **{k: {**meta.get(k, {}), **v} for k, v in facts.items()},
        }
