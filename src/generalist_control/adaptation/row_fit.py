"""Learning one plant's row of a grown policy, everything else frozen; scoring its loop.

The row is a parameter of its own, spliced into the embedding with
:func:`torch.func.functional_call`; ``adapt.unfreeze`` may name a few parameters besides.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor, nn

from generalist_control.adaptation.request import AdaptSettings
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.bank import ROWS, set_row
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import Plant
from generalist_control.simulation.comparison import ClosedLoopScore
from generalist_control.simulation.simulate import simulate_many
from generalist_control.training.settings import ClosedLoopValSettings

__all__ = [
    "LoopScore",
    "fit_row",
    "learned_parameters",
    "nearest_row",
]

#: The row's name inside the network (``ROWS`` without ``net.``).
_NET_ROWS = ROWS.removeprefix("net.")

#: Windows the start rows are compared on (a random subset when there are more).
_COMPARED = 4096


def _spliced(frozen: Tensor, tag: int, row: Tensor) -> Tensor:
    """The embedding's weight with row ``tag`` replaced by ``row`` (the others detached)."""
    return torch.cat([frozen[:tag], row[None], frozen[tag + 1 :]])


@torch.no_grad()
def nearest_row(
    policy: Policy, tag: int, tensors: Mapping[str, Tensor], candidates: Mapping[str, Tensor]
) -> tuple[str, dict[str, float]]:
    """The candidate row whose policy imitates the windows best, and every candidate's loss."""
    frozen = policy.state_dict()[ROWS]
    n = len(tensors["tag"])
    pick = torch.randperm(n, generator=torch.Generator().manual_seed(0))[:_COMPARED]
    batch = {k: v[pick] for k, v in tensors.items()}
    losses = {
        name: float(policy.errors(batch, {_NET_ROWS: _spliced(frozen, tag, row)})[0].mean())
        for name, row in candidates.items()
    }
    finite = {k: v for k, v in losses.items() if v == v}
    return min(finite, key=finite.__getitem__), losses


def learned_parameters(policy: Policy, unfreeze: Sequence[str]) -> dict[str, nn.Parameter]:
    """The network's parameters ``unfreeze`` names (each a dotted prefix of their names).

    Raises
    ------
    ValueError
        If a prefix names no parameter, or names the tag embedding (trained rows stay).
    """
    named = dict(policy.named_parameters())
    out: dict[str, nn.Parameter] = {}
    for prefix in unfreeze:
        hits = {k: p for k, p in named.items() if k == prefix or k.startswith(prefix + ".")}
        if not hits:
            parts = sorted({".".join(k.split(".")[:2]) for k in named})
            raise ValueError(
                f"adapt.unfreeze names {prefix!r}, which is no parameter of the policy; its "
                f"parts: {parts} (e.g. net.skip.gains)"
            )
        if ROWS in hits:
            raise ValueError(
                f"adapt.unfreeze names {prefix!r}, which holds the trained plants' rows "
                f"({ROWS}): the new row is always learned, the others never"
            )
        out.update(hits)
    return out


@contextmanager
def _learning(policy: Policy, learned: Mapping[str, nn.Parameter]) -> Iterator[None]:
    """Only ``learned`` parameters take gradients inside; afterwards every one does again."""
    flags = {k: p.requires_grad for k, p in policy.named_parameters()}
    for k, p in policy.named_parameters():
        p.requires_grad_(k in learned)
    was_training = policy.training
    policy.train()
    try:
        yield
    finally:
        for k, p in policy.named_parameters():
            p.requires_grad_(flags[k])
        policy.train(was_training)


def fit_row(
    policy: Policy,
    tag: int,
    tensors: Mapping[str, Tensor],
    settings: AdaptSettings,
    learned: Mapping[str, nn.Parameter],
    seed: int,
) -> list[float]:
    """Fit row ``tag`` (and ``learned``) on ``tensors``; return each epoch's mean loss.

    Every other row and every parameter not in ``learned`` is left bit for bit as it was.
    """
    frozen = policy.state_dict()[ROWS].clone()
    row = nn.Parameter(frozen[tag].clone())
    optimiser = torch.optim.Adam([row, *learned.values()], lr=settings.lr)
    generator = torch.Generator().manual_seed(seed)
    n, losses = len(tensors["tag"]), []
    with _learning(policy, learned):
        for _ in range(settings.epochs):
            total = 0.0
            for idx in torch.randperm(n, generator=generator).split(settings.batch_size):
                batch = {k: v[idx] for k, v in tensors.items()}
                loss = policy.errors(batch, {_NET_ROWS: _spliced(frozen, tag, row)})[0].mean()
                optimiser.zero_grad(set_to_none=True)
                loss.backward()
                optimiser.step()
                total += loss.item() * len(idx)
            losses.append(total / n)
    set_row(policy, tag, row)
    return losses


class LoopScore:
    """The plant's step error in closed loop relative to its LQI's (1: diverged).

    On the steps of ``closed_loop_val``, LQI simulated once.
    """

    def __init__(self, plant: Plant, scoring: ClosedLoopValSettings) -> None:
        self.plant = plant
        self.steps = ClosedLoopScore([plant], scoring.amplitudes, scoring.duration)

    def __call__(self, policy: Policy, meta: dict[str, Any]) -> float:
        """The score of ``policy`` (lower is better, at most 1)."""
        with torch.inference_mode():
            return self.steps(RuntimeAdapter(PolicyRuntime(policy, meta)))[self.plant.name]

    def diverges(self, policy: Policy, meta: dict[str, Any]) -> bool:
        """Whether a step run of ``policy`` diverges (a state beyond the simulator's bound)."""
        with torch.inference_mode():
            runs = simulate_many(self.steps.runs, RuntimeAdapter(PolicyRuntime(policy, meta)))
        return any(bool(run.diverged.any()) for run in runs)
