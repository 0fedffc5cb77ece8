"""Where the plant reaches the network (``model.plant``): a window and tag -> the plant's code.

:class:`TagEmbedding` is the paper's (the tag's learned row); :class:`InferredPlant` weighs
the same rows by an identity head read from the window (the tag a training label only).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from generalist_control.common.sections import require_int, require_nonnegative
from generalist_control.model.identifier import TransitionSet
from generalist_control.plants.definition import MAX_ORDER, Plant

__all__ = ["EVIDENCE_WEIGHT", "InferredPlant", "PlantPart", "PlantReading", "TagEmbedding"]

#: The initial weight of each plant's one-step-model evidence in its identity logit.
EVIDENCE_WEIGHT = 4.0


@dataclass(frozen=True)
class PlantReading:
    """What a plant part that infers the plant read from the window."""

    logits: Tensor | None  #: (B, n_tags): the identity head's logits (None: no head)
    summary: Tensor  #: (B, features): the identifier's state, what a context skip reads
    evidence: Tensor | None  #: (B, n_tags): each plant's one-step model's evidence


class PlantPart(nn.Module):
    """What every plant part offers: its code (``forward``), its tags, its own loss, its fits.

    The fits: rows computed from plants' models (:meth:`plant_rows`), and what it computes
    from the training plants (:meth:`fit_plants`).
    """

    needs: tuple[str, ...] = ()  #: window channels the part reads
    summary_size = 0  #: size of what it adds to a context skip's summary
    n_tags: int  #: system tags ``0 .. n_tags - 1``
    reads_tag = True  #: the code is the tag's row: a new plant needs a row (``adapt``)
    learned_rows = False  #: that row is a learned parameter (``adapt`` learns a new plant's)
    maps_states = False  #: the normaliser maps each plant's state into a frame of its own

    def loss(self, reading: PlantReading | None, tag: Tensor) -> tuple[Tensor, Tensor] | None:
        """The part's own training term: ``(logged, weighted)``, or None where it has none.

        ``logged`` is reported as ``train/identity``; ``weighted`` is added to the loss.
        """
        return None

    def plant_rows(self, plants: Sequence[Plant], width: int) -> dict[str, Tensor] | None:
        """Rows of ``plants`` from their models alone; None: the part cannot take a plant so.

        Stacked per-tag entries keyed as in a policy's ``state_dict`` (windows ``width`` wide).
        """
        return None

    def fit_plants(self, plants: Sequence[Plant]) -> None:
        """What the part computes from the training ``plants`` (nothing here).

        Training only, once the normaliser and the rows of :meth:`plant_rows` are in.
        """


class TagEmbedding(PlantPart):
    """The tag's row of a learned embedding, ``dim`` wide (the paper's system-tag input)."""

    learned_rows = True

    def __init__(self, dim: int, n_tags: int = 25) -> None:
        super().__init__()
        self.n_tags = require_int("model.plant.n_tags", n_tags)
        self.rows = nn.Embedding(self.n_tags, dim)

    def forward(
        self, state: Tensor | None, mask: Tensor | None, ref: Tensor | None, tag: Tensor
    ) -> tuple[Tensor, PlantReading | None]:
        """The rows (B, dim) of ``tag``; nothing read from the window."""
        return self.rows(tag), None


class InferredPlant(PlantPart):
    """The plant inferred from the window: the embedding's rows weighed by an identity head.

    Parameters
    ----------
    identifier : callable
        Builds the :class:`~generalist_control.model.identifier.TransitionSet`; its models,
        if any, get the rows (detached) and their evidence joins the identity logits.
    noise : float
        Training only: white noise on the identifier's copy of the plant states, std per
        window uniform in ``[0, noise]`` (normalised units). 0: none.
    loss_weight : float
        Weight of :meth:`loss` beside the imitation loss (> 0: the head is trained by it).
    """

    needs: tuple[str, ...] = ("previous_control",)
    reads_tag = False

    def __init__(
        self,
        dim: int,
        identifier: Callable[..., TransitionSet],
        n_tags: int = 25,
        noise: float = 0.0,
        loss_weight: float = 1.0,
    ) -> None:
        super().__init__()
        self.n_tags = require_int("model.plant.n_tags", n_tags)
        self.noise = require_nonnegative("model.plant.noise", noise)
        self.loss_weight = require_nonnegative("model.plant.loss_weight", loss_weight)
        if self.loss_weight == 0:
            raise ValueError(
                "model.plant.loss_weight must be > 0: the identity head that weighs the rows "
                "is trained by this loss alone"
            )
        self.rows = nn.Embedding(self.n_tags, dim)
        self.identifier = identifier(state_dim=MAX_ORDER, hidden=dim)
        evidence = self.n_tags if self.identifier.models is not None else 0
        self.summary_size = dim + evidence
        self.head = nn.Linear(dim + evidence, self.n_tags)
        if evidence:  # each plant's evidence starts as its logit (x EVIDENCE_WEIGHT)
            with torch.no_grad():
                self.head.weight[:, dim:] = EVIDENCE_WEIGHT * torch.eye(evidence)

    def forward(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, PlantReading]:
        """The inferred code (B, dim) and what was read; ``tag`` is not used."""
        noise = self.noise if self.training else 0.0
        # detached: the models' fit moves their own layer, never the rows the law reads
        rows = self.rows.weight.detach() if self.identifier.models is not None else None
        summary = self.identifier.read(state, mask, rows, noise)
        logits = self.head(summary)
        code = torch.softmax(logits, dim=-1) @ self.rows.weight
        evidence = summary[:, -self.n_tags :] if rows is not None else None
        return code, PlantReading(logits=logits, summary=summary, evidence=evidence)

    def loss(self, reading: PlantReading | None, tag: Tensor) -> tuple[Tensor, Tensor] | None:
        """The head's cross-entropy against ``tag``, and it plus the models' fit, weighed."""
        if reading is None or reading.logits is None:
            return None
        cross_entropy = F.cross_entropy(reading.logits, tag)
        models = self.identifier.models
        term = cross_entropy
        if models is not None and reading.evidence is not None:
            term = term + models.fit_loss(reading.evidence, tag)
        return cross_entropy, self.loss_weight * term
