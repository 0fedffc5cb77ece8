"""The in-context route: the plant read from the policy's own window, no row per plant.

The window's transitions are encoded with no per-plant parameter; over a plant family the
code also learns to predict the plant's card (a training target, never an input). Its
normaliser rows come from each plant's operating data: RMS scales, the state whitened by its
covariance (``docs/notes/family-policy.md``).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from generalist_control.common.schema import require_int, require_nonnegative
from generalist_control.model.card import CARD_FEATURES
from generalist_control.model.identifier import TransitionSet
from generalist_control.model.output import PlantReading
from generalist_control.model.plant import PlantPart
from generalist_control.plants.definition import MAX_ORDER

__all__ = ["ContextPlant"]


class ContextPlant(PlantPart):
    """The plant's code from the window's transitions alone (see the module docstring).

    Parameters
    ----------
    dim : int
        Size of the code (the network's ``hidden``); given by the network.
    identifier : callable
        Builds the encoder (``identifier(state_dim=..., hidden=dim)``, a
        :class:`~generalist_control.model.identifier.TransitionSet` without models).
    n_tags : int
        The normaliser's rows (one per training plant); nothing learned is per plant.
    noise : float
        Training only: white noise on the encoder's copy of each window's plant states, std
        per window uniform in ``[0, noise]`` (normalised units). 0: none.
    card_weight : float
        Weight of the card-prediction term (:meth:`loss`); 0: none.
    duration : float
        Seconds of the nominal step the card targets' frames are taken over.

    Attributes
    ----------
    targets : Tensor, shape (n_tags, CARD_FEATURES)
        Each training plant's standardised card (zero where none: :attr:`has_target`).
    """

    needs: tuple[str, ...] = ("previous_control",)
    #: The normaliser whitens each plant's state over its data (``Normaliser.state_map``).
    maps_states = True

    targets: Tensor
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
