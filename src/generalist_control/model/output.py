"""What the network returns: :class:`NetOutput`, and :class:`PlantReading` of an inferred plant."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["NetOutput", "PlantReading"]


@dataclass(frozen=True)
class PlantReading:
    """What a plant part that infers the plant read from the window."""

    logits: Tensor | None  #: (B, n_tags): the identity head's logits (None: no head)
    summary: Tensor  #: (B, features): the identifier's state, what a context skip reads
    evidence: Tensor | None  #: (B, n_tags): each plant's one-step model's evidence


@dataclass(frozen=True)
class NetOutput:
    """One forward pass of :class:`~generalist_control.model.network.GeneralistNetwork`."""

    control: Tensor  #: (B, horizon), normalised units divided by the window scale
    gates: Tensor  #: (B, experts), the mixture's softmax weights
    scale: Tensor  #: (B, 1), each window's scale (ones without window scaling)
    plant: PlantReading | None  #: what an inferred plant part read (None: by its tag)
