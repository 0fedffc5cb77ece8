"""What the network returns: :class:`NetOutput`, and :class:`PlantReading` of an inferred plant."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["NetOutput", "PlantReading"]


@dataclass(frozen=True)
class PlantReading:
    """What a plant part that infers the plant read from the window.

    Attributes
    ----------
    logits : Tensor or None, shape (B, n_tags)
        The identity head's logits over the training plants (None: a part without one).
    summary : Tensor, shape (B, features)
        The identifier's state (with its models' evidence last): what a context skip reads.
    evidence : Tensor or None, shape (B, n_tags)
        Each plant's one-step model's evidence on the window (None without models).
    """

    logits: Tensor | None
    summary: Tensor
    evidence: Tensor | None


@dataclass(frozen=True)
class NetOutput:
    """One forward pass of :class:`~generalist_control.model.network.GeneralistNetwork`.

    Attributes
    ----------
    control : Tensor, shape (B, horizon)
        The controls in normalised units divided by the window scale.
    gates : Tensor, shape (B, experts)
        The mixture's softmax gate weights (rows sum to one).
    scale : Tensor, shape (B, 1)
        Each window's scale (its peak; ones without window scaling).
    plant : PlantReading or None
        What an inferred plant part read (None when the plant is given by its tag).
    """

    control: Tensor
    gates: Tensor
    scale: Tensor
    plant: PlantReading | None
