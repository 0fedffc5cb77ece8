"""A trained policy grown by one plant: a new tag, its embedding row and its normaliser scales.

Every trained parameter and buffer is copied bit for bit; the new row starts where the caller
says and its scales are the RMS of the plant's windows, as training sets every row. A
tag-free policy needs only the scales, on a free row (:func:`with_scales`).
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping

import torch
from torch import Tensor

from generalist_control.model.normalise import Normaliser
from generalist_control.model.plant import InferredPlant, TagEmbedding
from generalist_control.model.policy import Policy

__all__ = [
    "ROWS",
    "SCALES",
    "RecipeError",
    "check_growable",
    "free_rows",
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


def check_growable(policy: Policy, source: str = "the policy") -> None:
    """Refuse a policy whose recipe cannot take a new row, naming what to do instead.

    Raises
    ------
    RecipeError
        For a tag-free policy (it needs no row: name the plant and evaluate it directly),
        or for a plant part this module does not know.
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


def plant_scales(state: Tensor, mask: Tensor, ref: Tensor, target: Tensor) -> dict[str, Tensor]:
    """The normaliser's buffers for one plant, fitted on its windows (one row each).

    Keyed as in a policy's ``state_dict`` (:data:`SCALES`); the row is marked seen.
    """
    one = Normaliser(1, state.shape[-1])
    one.fit(state, mask, ref, torch.zeros(len(state), dtype=torch.long), target)
    return {f"normaliser.{k}": v.detach().clone() for k, v in one.named_buffers()}


def start_rows(policy: Policy, tags: Iterable[int]) -> dict[str, Tensor]:
    """Where a new row may start: ``mean`` of the rows of ``tags`` (the trained plants).

    The rows of tags no plant was trained on (e.g. held-out plants' catalogue tags) are
    random, so only ``tags`` count.
    """
    rows = policy.state_dict()[ROWS]
    chosen = torch.as_tensor(sorted(set(tags)), dtype=torch.long)
    if chosen.numel() == 0:
        raise ValueError("the policy names no trained plant (meta tags): no row to start from")
    return {"mean": rows[chosen].mean(0)}


def grow_policy(policy: Policy, row: Tensor, scales: Mapping[str, Tensor]) -> Policy:
    """``policy`` with one more tag, ``n_tags``: its row ``row``, its scales ``scales``.

    Every other parameter and buffer is copied bit for bit; the policy returned is in eval
    mode, ``policy`` itself is not changed.

    Raises
    ------
    RecipeError
        If the recipe cannot take a row (:func:`check_growable`), or a parameter other than
        the embedding and the normaliser is sized by the number of tags.
    """
    check_growable(policy)
    old = policy.state_dict()
    n = policy.net.n_tags
    config = copy.deepcopy(policy.config)
    config["plant"] = {**config["plant"], "n_tags": n + 1}
    with torch.random.fork_rng():  # the fresh network's random start is thrown away
        grown = Policy(config)
    state: dict[str, Tensor] = {}
    for key, fresh in grown.state_dict().items():
        if key == ROWS:
            state[key] = torch.cat([old[key], row.detach().to(old[key].dtype)[None]])
        elif key in SCALES:
            state[key] = torch.cat([old[key], scales[key].to(old[key].dtype)])
        elif old[key].shape != fresh.shape:
            raise RecipeError(f"{key} is sized by the number of tags: a new row cannot be added")
        else:
            state[key] = old[key].clone()
    grown.load_state_dict(state)
    return grown.eval()


def set_row(policy: Policy, tag: int, row: Tensor) -> None:
    """Write ``row`` into the embedding's row ``tag``, in place; nothing else is touched."""
    with torch.no_grad():
        policy.get_parameter(ROWS)[tag].copy_(row)


def free_rows(policy: Policy, used: Iterable[int]) -> list[int]:
    """Tags of ``policy`` that no plant in ``used`` (its meta's tags) holds."""
    taken = set(int(t) for t in used)
    return [t for t in range(policy.net.n_tags) if t not in taken]


def with_scales(policy: Policy, tag: int, scales: Mapping[str, Tensor]) -> Policy:
    """A copy of ``policy`` whose normaliser row ``tag`` holds ``scales``; nothing else changes.

    For a tag-free policy meeting a plant it never saw: the plant is named on a free row
    (:func:`free_rows`) whose scales are fitted on its windows (:func:`plant_scales`).
    """
    state = {k: v.clone() for k, v in policy.state_dict().items()}
    for key in SCALES:
        state[key][tag] = scales[key][0].to(state[key].dtype)
    with torch.random.fork_rng():
        named = Policy(policy.config)
    named.load_state_dict(state)
    return named.eval()
