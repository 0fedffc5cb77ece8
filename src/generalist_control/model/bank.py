"""A policy's per-tag rows: those its plant part computes from plants' models, growing by one.

A grown policy copies every trained parameter and buffer bit for bit; its new row is a card
(nothing learned), scales fitted on the plant's windows, or a tag embedding's row to learn.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping, Sequence

import torch
from torch import Tensor

from generalist_control.model.normalise import Normaliser
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import Plant

__all__ = [
    "ROWS",
    "SCALES",
    "NoModelRowError",
    "RecipeError",
    "add_plant",
    "add_plants",
    "add_rows",
    "check_growable",
    "fit_model_rows",
    "grow_policy",
    "plant_scales",
    "set_row",
    "start_rows",
    "with_scales",
]

#: The tag embedding's rows in a policy's ``state_dict``.
ROWS = "net.plant.rows.weight"

#: The normaliser's per-tag buffers in a policy's ``state_dict``.
SCALES = tuple(f"normaliser.{k}" for k in ("state_scale", "ref_scale", "control_scale", "seen"))


class RecipeError(ValueError):
    """A policy whose recipe cannot take a new plant's row; the message says what to do."""


class NoModelRowError(ValueError):
    """A policy whose plant part cannot take a plant from its model (no card bank)."""


@torch.no_grad()
def fit_model_rows(policy: Policy, plants: Sequence[Plant], standardise: bool = True) -> None:
    """After the normaliser's fit: the plant part's rows of ``plants`` at their tags, in place.

    The rows its part computes from the plants' models (a card bank's); with ``standardise``
    (training), also the part's fit on them; without, rows written into a trained bank.

    Raises
    ------
    ValueError
        If a plant's tag lies outside the part's rows.
    """
    part = policy.net.plant
    rows = part.plant_rows(plants, policy.width)
    if rows is not None:
        bad = [p.name for p in plants if not 0 <= p.tag < part.n_tags]
        if bad or not plants:
            raise ValueError(
                f"plants {bad} have tags outside the bank's rows 0..{part.n_tags - 1}"
            )
        tags = torch.as_tensor([p.tag for p in plants], dtype=torch.long)
        buffers = dict(policy.named_buffers())
        for key, value in rows.items():
            buffers[key][tags] = value.to(buffers[key].dtype)
    if standardise:
        part.fit_plants(plants)


def _fresh(policy: Policy, n_tags: int) -> Policy:
    """A policy of ``policy``'s config with ``n_tags`` tags; its random start is thrown away."""
    config = copy.deepcopy(policy.config)
    config["plant"] = {**config["plant"], "n_tags": n_tags}
    with torch.random.fork_rng():
        return Policy(config)


def add_rows(policy: Policy, rows: Mapping[str, Tensor]) -> Policy:
    """A copy of ``policy`` (bit for bit) with more tags, its per-tag entries ``rows``.

    One tag per leading entry of ``rows`` (each entry holds as many).

    Raises
    ------
    RecipeError
        If an entry sized by the number of tags is missing from ``rows``.
    """
    old = policy.state_dict()
    grown = _fresh(policy, policy.net.n_tags + len(next(iter(rows.values()))))
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


def add_plant(policy: Policy, plant: Plant) -> Policy:
    """``policy`` grown by ``plant``'s row computed from its model (:func:`add_plants`)."""
    return add_plants(policy, [plant])


def add_plants(policy: Policy, plants: Sequence[Plant]) -> Policy:
    """``policy`` grown by the rows of ``plants``, in order, computed from their models.

    Raises
    ------
    NoModelRowError
        Naming the plant part, if it computes no row from a model (no card bank).
    """
    rows = policy.net.plant.plant_rows(list(plants), policy.width)
    if rows is None:
        raise NoModelRowError(type(policy.net.plant).__name__)
    return add_rows(policy, rows)


def plant_scales(state: Tensor, mask: Tensor, ref: Tensor, target: Tensor) -> dict[str, Tensor]:
    """One plant's normaliser row fitted on its windows, keyed as in a policy's ``state_dict``."""
    rows = Normaliser(1, state.shape[-1])
    rows.fit(state, mask, ref, torch.zeros(len(state), dtype=torch.long), target)
    return {f"normaliser.{k}": v.detach().clone() for k, v in rows.named_buffers()}


def check_growable(policy: Policy, source: str = "the policy") -> None:
    """Refuse a policy whose plant part is no tag embedding, naming what to do instead.

    Raises
    ------
    RecipeError
        For a tag-free policy (it needs no row) or any other part.
    """
    plant = policy.net.plant
    if not plant.reads_tag:
        raise RecipeError(
            f"{source} is tag-free (model.plant: {type(plant).__name__}): it reads the plant "
            "from the window and has no row to learn for a new plant. Evaluate it directly: "
            "adapt.learn=false names the plant and fits its normaliser scales, nothing learned"
        )
    if not plant.learned_rows:
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
    named = _fresh(policy, policy.net.n_tags)
    named.load_state_dict(state)
    return named.eval()
