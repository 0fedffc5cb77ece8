"""A policy's per-plant rows that are computed, not learned: the card bank and its frames.

Training fills them for its plants (:func:`fit_cards`); a plant never seen grows the policy
by one row (:func:`add_plant`), nothing learned. A tag embedding's rows are learned: such a
policy cannot grow here.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from generalist_control.model.card import CardFrame, CardPlant, card_features, card_frame
from generalist_control.model.context import ContextPlant
from generalist_control.model.normalise import Normaliser
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import MAX_ORDER, Plant

#: Smallest spread of a descriptor entry (an entry every training card shares).
STD_FLOOR = 1e-3

__all__ = [
    "NoModelRowError",
    "add_card",
    "add_plant",
    "add_rows",
    "add_scales",
    "card_part",
    "data_rows",
    "fit_cards",
    "fit_model_rows",
    "fit_targets",
    "frame_rows",
]


def card_part(policy: Policy) -> CardPlant:
    """The policy's card part, or a ``ValueError`` saying the policy has none."""
    part = policy.net.plant
    if not isinstance(part, CardPlant):
        raise ValueError(
            f"the policy reaches the plant through {type(part).__name__}, not a model card "
            "(model.plant: card)"
        )
    return part


def frame_rows(frame: CardFrame, width: int) -> dict[str, Tensor]:
    """The normaliser's buffers (one row each) for a card's frame, ``width`` window entries.

    Entry ``MAX_ORDER`` is the error integral, a last entry beyond it the previous control;
    padded state entries get the scale 1 and a zero row of the map.
    """
    n = len(frame.state)
    state = torch.ones(1, width, dtype=torch.float64)
    state[0, :n] = torch.as_tensor(frame.state)
    if width > MAX_ORDER:
        state[0, MAX_ORDER] = frame.integral
    if width > MAX_ORDER + 1:
        state[0, -1] = frame.control
    state_map = torch.zeros(1, MAX_ORDER, MAX_ORDER, dtype=torch.float64)
    state_map[0, :n, :n] = torch.as_tensor(frame.map)
    return {
        "normaliser.state_scale": state,
        "normaliser.ref_scale": torch.tensor([frame.reference], dtype=torch.float64),
        "normaliser.control_scale": torch.tensor([frame.control], dtype=torch.float64),
        "normaliser.seen": torch.ones(1, dtype=torch.bool),
        "normaliser.state_map": state_map,
    }


def _rows(policy: Policy, plants: Sequence[Plant]) -> dict[str, Tensor]:
    """Cards and normaliser rows of ``plants``, stacked in their order."""
    part = card_part(policy)
    rows: dict[str, list[Tensor]] = {}
    for p in plants:
        features, frame = part.card(p)
        rows.setdefault("net.plant.cards", []).append(torch.as_tensor(features)[None])
        for k, v in frame_rows(frame, policy.width).items():
            rows.setdefault(k, []).append(v)
    return {k: torch.cat(v) for k, v in rows.items()}


@torch.no_grad()
def fit_cards(policy: Policy, plants: Sequence[Plant], standardise: bool = True) -> None:
    """Fill ``policy``'s bank and normaliser rows at each plant's tag, in place.

    With ``standardise`` (training), the cards' mean and spread over these rows become the
    part's standardisation; without, it is kept (rows written into a trained bank). Rows of
    tags no plant holds keep what they held.

    Raises
    ------
    ValueError
        If the policy has no card part, or a plant's tag lies outside the bank.
    """
    part = card_part(policy)
    bad = [p.name for p in plants if not 0 <= p.tag < part.n_tags]
    if bad or not plants:
        raise ValueError(f"plants {bad} have tags outside the bank's rows 0..{part.n_tags - 1}")
    tags = torch.as_tensor([p.tag for p in plants], dtype=torch.long)
    buffers = dict(policy.named_buffers())
    for key, rows in _rows(policy, plants).items():
        buffers[key][tags] = rows.to(buffers[key].dtype)
    if not standardise:
        return
    cards = part.cards[tags].double()
    part.card_mean.copy_(cards.mean(0))
    part.card_std.copy_(cards.std(0, unbiased=False).clamp(min=STD_FLOOR))


def fit_model_rows(policy: Policy, plants: Sequence[Plant]) -> None:
    """Fill the rows a policy computes from its plants' models; else nothing.

    Called by training after the normaliser's fit on the data: the card bank replaces the
    fitted rows; an in-context part's card targets (training only) are filled beside them.
    """
    part = policy.net.plant
    if isinstance(part, CardPlant):
        fit_cards(policy, plants)
    elif isinstance(part, ContextPlant) and part.card_weight > 0:
        fit_targets(part, plants)


@torch.no_grad()
def fit_targets(part: ContextPlant, plants: Sequence[Plant]) -> None:
    """The in-context part's card targets: each plant's card, standardised over ``plants``."""
    tags = torch.as_tensor([p.tag for p in plants], dtype=torch.long)
    cards = torch.stack(
        [torch.as_tensor(card_features(p, card_frame(p, part.duration))) for p in plants]
    )
    spread = cards.std(0, unbiased=False).clamp(min=STD_FLOOR) if len(plants) > 1 else 1.0
    part.targets[tags] = ((cards - cards.mean(0)) / spread).to(part.targets.dtype)
    part.has_target[tags] = True


def add_rows(policy: Policy, rows: Mapping[str, Tensor]) -> Policy:
    """``policy`` with one more tag whose per-tag buffers hold ``rows`` (one row each).

    Every other parameter and buffer is copied bit for bit; ``policy`` is not changed.

    Raises
    ------
    ValueError
        If an entry sized by the number of tags is missing from ``rows`` (a learned per-tag
        parameter: a tag embedding has no row for a plant it never saw).
    """
    old = policy.state_dict()
    config = copy.deepcopy(policy.config)
    config["plant"] = {**config["plant"], "n_tags": policy.net.n_tags + 1}
    with torch.random.fork_rng():  # the fresh network's random start is thrown away
        grown = Policy(config)
    state: dict[str, Tensor] = {}
    for key, fresh in grown.state_dict().items():
        if key in rows:
            state[key] = torch.cat([old[key], rows[key].to(old[key].dtype)])
        elif old[key].shape != fresh.shape:
            raise ValueError(f"{key} is learned per tag: a plant never trained on has no row")
        else:
            state[key] = old[key].clone()
    grown.load_state_dict(state)
    return grown.eval()


def add_card(policy: Policy, plant: Plant) -> Policy:
    """``policy`` grown by one row: ``plant``'s card and frame, tag the old ``n_tags``."""
    return add_rows(policy, _rows(policy, [plant]))


class NoModelRowError(ValueError):
    """A policy whose plant part cannot take a plant from its model (no card bank)."""


def add_plant(policy: Policy, plant: Plant) -> Policy:
    """``policy`` grown by ``plant``'s row computed from its model (the card route only).

    Raises
    ------
    NoModelRowError
        If the policy's plant part learns its rows (a tag embedding) or reads the plant from
        the window with scales of the plant's data (in context): naming the part.
    """
    part = policy.net.plant
    if not isinstance(part, CardPlant):
        raise NoModelRowError(type(part).__name__)
    return add_card(policy, plant)


def data_rows(
    policy: Policy, state: Tensor, mask: Tensor, ref: Tensor, target: Tensor
) -> dict[str, Tensor]:
    """A new plant's normaliser row fitted on its windows, as training fits every row."""
    one = Normaliser(1, policy.width, policy.normaliser.mapped)
    one.fit(state, mask, ref, torch.zeros(len(state), dtype=torch.long), target)
    return {f"normaliser.{k}": v.detach().clone() for k, v in one.named_buffers()}


def add_scales(policy: Policy, scales: Mapping[str, Tensor]) -> Policy:
    """``policy`` grown by one normaliser row, ``scales`` (keys as in its ``state_dict``).

    The plant part's own per-tag buffers (an in-context part's card targets, training only)
    get an empty row.
    """
    n = policy.net.n_tags
    rows = dict(scales)
    for key, value in policy.net.plant.named_buffers(prefix="net.plant"):
        if key not in rows and value.shape[:1] == (n,):
            rows[key] = torch.zeros_like(value[:1])
    return add_rows(policy, rows)
