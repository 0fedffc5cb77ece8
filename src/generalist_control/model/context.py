"""The in-context route: the plant read from the window's transitions, no parameter per plant.

The code may also learn to predict the plant's card (a training target, never an input);
``docs/notes/family-policy.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from generalist_control.common.sections import require_int, require_nonnegative
from generalist_control.model.card import CARD_FEATURES, STD_FLOOR, card_features, card_frame
from generalist_control.model.identifier import TransitionSet
from generalist_control.model.plant import PlantPart, PlantReading
from generalist_control.plants.definition import MAX_ORDER, Plant

__all__ = ["ContextPlant"]


class ContextPlant(PlantPart):
    """The plant's code from the window's transitions alone (see the module docstring).

    ``identifier`` builds a :class:`~generalist_control.model.identifier.TransitionSet`
    without models; ``noise`` as :class:`~generalist_control.model.plant.InferredPlant`'s;
    ``card_weight`` weighs the card-prediction term (:meth:`loss`; 0: none), whose targets'
    frames are taken over ``duration`` seconds of the nominal step.
    """

    needs: tuple[str, ...] = ("previous_control",)
    maps_states = True  #: the normaliser whitens each plant's state over its data

    targets: Tensor  #: (n_tags, CARD_FEATURES): each training plant's standardised card
    has_target: Tensor

    def __init__(
        self,
        dim: int,
        identifier: Callable[..., TransitionSet],
        n_tags: int = 25,
        noise: float = 0.0,
        card_weight: float = 0.0,
        duration: float = 10.0,
    ) -> None:
        super().__init__()
        self.n_tags = require_int("model.plant.n_tags", n_tags)
        self.noise = require_nonnegative("model.plant.noise", noise)
        self.card_weight = require_nonnegative("model.plant.card_weight", card_weight)
        self.duration = require_nonnegative("model.plant.duration", duration)
        self.identifier = identifier(state_dim=MAX_ORDER, hidden=dim)
        if self.identifier.models is not None:
            raise ValueError(
                "model.plant.identifier.models must be null: one-step models are per plant, "
                "and the in-context route has no per-plant parameter"
            )
        self.summary_size = dim  # what a context skip reads beside the law's summary
        self.card_head = nn.Linear(dim, CARD_FEATURES)
        self.register_buffer("targets", torch.zeros(self.n_tags, CARD_FEATURES))
        self.register_buffer("has_target", torch.zeros(self.n_tags, dtype=torch.bool))

    def forward(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, PlantReading]:
        """The code (B, dim) read from the window; ``tag`` is not used."""
        noise = self.noise if self.training else 0.0
        code = self.identifier.read(state, mask, None, noise)
        return code, PlantReading(logits=None, summary=code, evidence=None)

    @torch.no_grad()
    def fit_plants(self, plants: Sequence[Plant]) -> None:
        """The card targets (with :attr:`card_weight`): each plant's card, standardised."""
        if self.card_weight == 0:
            return
        tags = torch.as_tensor([p.tag for p in plants], dtype=torch.long)
        cards = torch.stack(
            [torch.as_tensor(card_features(p, card_frame(p, self.duration))) for p in plants]
        )
        spread = cards.std(0, unbiased=False).clamp(min=STD_FLOOR) if len(plants) > 1 else 1.0
        self.targets[tags] = ((cards - cards.mean(0)) / spread).to(self.targets.dtype)
        self.has_target[tags] = True

    def loss(self, reading: PlantReading | None, tag: Tensor) -> tuple[Tensor, Tensor] | None:
        """The card-prediction MSE over windows of plants with a card, and it weighed."""
        if reading is None or self.card_weight == 0:
            return None
        known = self.has_target[tag]
        if not bool(known.any()):
            return None
        err = (self.card_head(reading.summary[known]) - self.targets[tag[known]]) ** 2
        mse = err.mean()
        return mse, self.card_weight * mse
