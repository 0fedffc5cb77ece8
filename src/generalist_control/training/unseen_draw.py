"""Plants no training saw, met zero-shot: ``val/closed_loop`` scores new members of a family.

Scored on its training plants alone, the closed-loop check keeps the checkpoint that best
controls what it was fitted on; a family route is meant for plants it never saw, so its
checkpoint is chosen on those too (docs/notes/family-policy.md, experiment 13).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from generalist_control.data.generation import generate_demos
from generalist_control.deploy.runtime_plants import integral_facts
from generalist_control.model.bank import RecipeError, add_plants, add_scales, plant_scales
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import Plant
from generalist_control.simulation.family_draw import draw_family, read_families

__all__ = ["UnseenDraw"]

_FIELDS = ("state", "mask", "ref", "target")  #: the windows' fields the scales are fitted on


@dataclass(frozen=True)
class UnseenDraw:
    """A family draw a policy meets as it would at deployment, nothing learned.

    A plant part that computes a plant's row from its model (the card) gets the rows from
    the plants' models; any other part (in context) the normaliser rows fitted on the
    plants' LQI demonstrations by the data recipe, as ``reports/held_out`` does.
    """

    plants: tuple[Plant, ...]
    scales: dict[str, Tensor] | None  #: the normaliser rows, where the part computes none

    @classmethod
    def draw(
        cls,
        family: Mapping[str, Any],
        policy: Policy,
        data: Mapping[str, Any],
        history: int,
        horizon: int,
    ) -> UnseenDraw:
        """``family`` (a ``conf/families`` group, plain types) drawn and met (:meth:`of`).

        Raises
        ------
        ValueError
            Naming the key: a family the generator refuses, too few plants that pass, or a
            plant part that learns a row per plant (a plant never trained on has none).
        """
        generator, settings = read_families(family)
        plants = draw_family(generator, settings.count, settings.checks).plants
        return cls.of(plants, policy, data, history, horizon)

    @classmethod
    def of(
        cls,
        plants: Sequence[Plant],
        policy: Policy,
        data: Mapping[str, Any],
        history: int,
        horizon: int,
    ) -> UnseenDraw:
        """``plants`` (tags ``0 .. k-1``: their places) as ``policy``'s plant part meets them.

        Raises
        ------
        ValueError
            If the plant part learns a row per plant (a plant never trained on has none).
        """
        plants = tuple(plants)
        if policy.net.plant.plant_rows(list(plants[:1]), policy.width) is not None:
            return cls(plants, None)
        demos = generate_demos(plants, {**data, "history": history, "horizon": horizon}, False)
        channels = policy.channels
        w = demos.windows(history, horizon, "integral" in channels, "previous_control" in channels)
        state, mask, ref, target = (torch.from_numpy(getattr(w, k)) for k in _FIELDS)
        plant = torch.from_numpy(w.tag).long()
        scales = plant_scales(state, mask, ref, target, policy.normaliser.mapped, plant)
        try:
            add_scales(policy, scales)
        except RecipeError as exc:
            raise ValueError(
                f"this policy cannot meet zero-shot ({exc}) a plant no training saw: train "
                "it with model/plant=card or context (or set train_families.validation=null)"
            ) from None
        return cls(plants, scales)

    def met(self, policy: Policy, meta: Mapping[str, Any]) -> tuple[Policy, dict[str, Any]]:
        """``policy`` grown by the draw's rows, and its meta naming the draw's plants."""
        grown = (
            add_plants(policy, self.plants)
            if self.scales is None
            else add_scales(policy, self.scales)
        )
        first, plants = policy.net.n_tags, self.plants
        facts = integral_facts(plants=plants)
        return grown, {
            **meta,
            "tags": {**meta["tags"], **{p.name: first + i for i, p in enumerate(plants)}},
            "orders": {**meta["orders"], **{p.name: p.order for p in plants}},
            **{k: {**meta.get(k, {}), **v} for k, v in facts.items()},
        }
