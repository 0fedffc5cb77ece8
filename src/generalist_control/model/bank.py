"""A policy's per-tag rows: the card bank computed from the plants' models, and growing by one.

A grown policy copies every trained parameter and buffer bit for bit; its new row is a card
(nothing learned), scales fitted on the plant's windows, or a tag embedding's row to learn.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping, Sequence

import torch
from torch import Tensor

from generalist_control.model.card import CardFrame, CardPlant, card_features, card_frame
from generalist_control.model.context import ContextPlant
from generalist_control.model.normalise import Normaliser
from generalist_control.model.plant import InferredPlant, TagEmbedding
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import MAX_ORDER, Plant

__all__ = [
    "ROWS",
    "SCALES",
    "NoModelRowError",
    "RecipeError",
    "add_card",
    "add_plant",
    "add_rows",
    "add_scales",
    "card_part",
    "check_growable",
    "fit_cards",
    "fit_model_rows",
    "fit_targets",
    "frame_rows",
    "grow_policy",
    "plant_scales",
    "set_row",
    "start_rows",
    "with_scales",
]

#: Smallest spread of a descriptor entry (an entry every training card shares).
STD_FLOOR = 1e-3

#: The tag embedding's rows in a policy's ``state_dict``.
ROWS = "net.plant.rows.weight"

#: The normaliser's per-tag buffers in a policy's ``state_dict``.
SCALES = tuple(f"normaliser.{k}" for k in ("state_scale", "ref_scale", "control_scale", "seen"))


class RecipeError(ValueError):
    """A policy whose recipe cannot take a new plant's row; the message says what to do."""


class NoModelRowError(ValueError):
    """A policy whose plant part cannot take a plant from its model (no card bank)."""


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

    With ``standardise`` (training), the cards' mean and spread become the part's
    standardisation; without, it is kept (rows written into a trained bank).

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
    """After the normaliser's fit: the card bank's rows, or an in-context part's card targets."""
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
    """A copy of ``policy`` (bit for bit) with one more tag, its per-tag entries ``rows``.

    Raises
    ------
    RecipeError
        If an entry sized by the number of tags is missing from ``rows``.
    """
    old = policy.state_dict()
    config = copy.deepcopy(policy.config)
    config["plant"] = {**config["plant"], "n_tags": policy.net.n_tags + 1}
    with torch.random.fork_rng():  # the fresh network's random start is thrown away
        grown = Policy(config)
    state: dict[str, Tensor] = {}
    for key, fresh in grown.state_dict().items():
        if key in rows:
            state[key] = torch.cat([old[key], rows[key].detach().to(old[key].dtype)])
        elif old[key].shape != fresh.shape:
            raise RecipeError(f"{key} is learned per tag: a plant never trained on has no row")
        else:
            state[key] = old[key].clone()
    grown.load_state_dict(state)
    return grown.eval()


def add_card(policy: Policy, plant: Plant) -> Policy:
    """``policy`` grown by one row: ``plant``'s card and frame, tag the old ``n_tags``."""
    return add_rows(policy, _rows(policy, [plant]))


def add_plant(policy: Policy, plant: Plant) -> Policy:
    """``policy`` grown by ``plant``'s row computed from its model (the card route only).

    Raises
    ------
    NoModelRowError
        Naming the plant part, if it is not a card bank.
    """
    if not isinstance(policy.net.plant, CardPlant):
        raise NoModelRowError(type(policy.net.plant).__name__)
    return add_card(policy, plant)


def plant_scales(
    state: Tensor, mask: Tensor, ref: Tensor, target: Tensor, mapped: bool = False
) -> dict[str, Tensor]:
    """One plant's normaliser row fitted on its windows, keyed as in a policy's ``state_dict``.

    ``mapped``: the policy's normaliser maps states (``Normaliser.mapped``).
    """
    one = Normaliser(1, state.shape[-1], mapped)
    one.fit(state, mask, ref, torch.zeros(len(state), dtype=torch.long), target)
    return {f"normaliser.{k}": v.detach().clone() for k, v in one.named_buffers()}


def add_scales(policy: Policy, scales: Mapping[str, Tensor]) -> Policy:
    """``policy`` grown by one normaliser row, ``scales``; the plant part's buffers get zeros."""
    rows = dict(scales)
    for key, value in policy.net.plant.named_buffers(prefix="net.plant"):
        if key not in rows and value.shape[:1] == (policy.net.n_tags,):
            rows[key] = torch.zeros_like(value[:1])
    return add_rows(policy, rows)


def check_growable(policy: Policy, source: str = "the policy") -> None:
    """Refuse a policy whose plant part is no tag embedding, naming what to do instead.

    Raises
    ------
    RecipeError
        For a tag-free policy (it needs no row) or any other part.
    """
    plant = policy.net.plant
    if isinstance(plant, InferredPlant):
        raise RecipeError(
            f"{source} is tag-free (model.plant: InferredPlant): it reads the plant from the "
            "window and has no row to learn for a new plant. Evaluate it directly: "
            "adapt.learn=false names the plant and fits its normaliser scales, nothing learned"
        )
    if not isinstance(plant, TagEmbedding):
        raise RecipeError(
            f"{source} reaches the plant through {type(plant).__name__}, not a tag embedding "
            "(model.plant: TagEmbedding): there is no row to add"
        )


def start_rows(policy: Policy, tags: Iterable[int]) -> dict[str, Tensor]:
    """Where a new row may start: ``mean`` of the rows of ``tags`` (the trained plants only)."""
    rows = policy.state_dict()[ROWS]
    chosen = torch.as_tensor(sorted(set(tags)), dtype=torch.long)
    if chosen.numel() == 0:
        raise ValueError("the policy names no trained plant (meta tags): no row to start from")
    return {"mean": rows[chosen].mean(0)}


def grow_policy(policy: Policy, row: Tensor, scales: Mapping[str, Tensor]) -> Policy:
    """``policy`` with one more tag: embedding row ``row``, normaliser row ``scales``."""
    check_growable(policy)
    return add_rows(policy, {ROWS: row[None], **{k: scales[k] for k in SCALES}})


def set_row(policy: Policy, tag: int, row: Tensor) -> None:
    """Write ``row`` into the embedding's row ``tag``, in place; nothing else is touched."""
    with torch.no_grad():
        policy.get_parameter(ROWS)[tag].copy_(row)


def with_scales(policy: Policy, tag: int, scales: Mapping[str, Tensor]) -> Policy:
    """A copy of ``policy`` whose normaliser row ``tag`` (a free one) holds ``scales``."""
    state = {k: v.clone() for k, v in policy.state_dict().items()}
    for key in SCALES:
        state[key][tag] = scales[key][0].to(state[key].dtype)
    with torch.random.fork_rng():
        named = Policy(policy.config)
    named.load_state_dict(state)
    return named.eval()
