"""The model card route: the plant reaches the network as a descriptor of its model.

A plant's frame and its descriptor in that frame (the expert's gain there) are computed from
its card (A, B, C, dt, Q, R) by stated rules, never fitted, so a new plant needs no training
(docs/notes/family-policy.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from generalist_control.common.sections import require_int, require_nonnegative
from generalist_control.model.plant import PlantPart
from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.lqi import design_lqi, sampled_closed_loop

__all__ = [
    "CARD_FEATURES",
    "STD_FLOOR",
    "CardFrame",
    "CardPlant",
    "card_features",
    "card_frame",
]

_W = MAX_ORDER + 1  # the augmented state [x; z], the integral last
#: Size of a descriptor (:func:`card_features`): the order mask, the padded gain.
CARD_FEATURES = MAX_ORDER + _W
#: RMS below this (a signal the step leaves at rest) gives the scale 1, as the normaliser does.
_TINY = 1e-12
#: Smallest spread of a descriptor entry (an entry every training card shares).
STD_FLOOR = 1e-3


class CardError(ValueError):
    """A card the route cannot serve (unobservable output, unfit for LQI); says why."""


@dataclass(frozen=True)
class CardFrame:
    """A plant's normalised realisation (:func:`card_frame`); RMS over the nominal unit step."""

    map: np.ndarray  #: (n, n): ``x -> q / s_q``, the state in the frame
    state: np.ndarray  #: (n,): RMS of ``x`` in its own coordinates
    integral: float  #: RMS of ``z``
    control: float  #: RMS of ``u``
    omega: float  #: the frame's time scale ``w`` (rad/s)
    gain: np.ndarray  #: (n + 1,): the expert's gain on the frame's ``[q; z]``, ``u = -gain w``
    reference: float = 1.0  #: the reference's scale (a unit step)


def _rms(v: np.ndarray) -> np.ndarray:
    """RMS over the first axis (1 where it is tiny)."""
    rms = np.sqrt(np.mean(np.square(v), axis=0))
    return np.where(rms > _TINY, rms, 1.0)


def _observability(plant: Plant, omega: float) -> np.ndarray:
    """The output and its derivatives scaled by ``omega``; refuses a non-minimal model."""
    rows = [plant.C[0]]
    for _ in range(plant.order - 1):
        rows.append(rows[-1] @ plant.A / omega)
    T = np.array(rows)
    if np.linalg.cond(T) > 1e12:
        raise CardError(
            f"plant '{plant.name}': its states are not observable from its output (the model "
            "is not minimal): give a minimal realisation (A, B, C) of the plant"
        )
    return T


def card_frame(plant: Plant, duration: float) -> CardFrame:
    """The plant's frame: scales over ``duration`` s of the expert's sampled unit-step loop.

    Raises
    ------
    CardError
        If the plant is unfit for LQI or its output does not observe every state.
    """
    try:
        gains = design_lqi(plant)
    except ValueError as exc:
        raise CardError(str(exc)) from None
    omega = float(np.exp(np.mean(np.log(np.abs(gains.poles)))))
    T = _observability(plant, omega)
    M = sampled_closed_loop(plant, gains)
    n, steps = plant.order, max(1, int(round(float(duration) / plant.dt)))
    drive = np.zeros(n + 1)
    drive[n] = plant.dt
    s, run = np.zeros(n + 1), np.empty((steps, n + 1))
    for k in range(steps):
        run[k] = s
        s = M @ s + drive
    rms = _rms(np.hstack([run, run[:, :n] @ T.T, -run @ gains.K.T]))
    frame_map = T / rms[n + 1 : 2 * n + 1, None]
    gain = np.append(gains.Kx @ np.linalg.inv(frame_map), gains.Ki * rms[n]) / rms[-1]
    return CardFrame(
        map=frame_map, state=rms[:n], integral=float(rms[n]),
        control=float(rms[-1]), omega=omega, gain=gain,
    )  # fmt: skip


def card_features(plant: Plant, frame: CardFrame) -> np.ndarray:
    """The plant's descriptor (:data:`CARD_FEATURES`,) in ``frame``: mask and gain.

    The order mask, then ``asinh`` of the expert's gain on the frame's ``[q; z]``
    (:attr:`CardFrame.gain`), padded. The gain alone: a descriptor of the model itself (its
    rates, step and frequency responses, the weights) measured worse off the family
    (docs/notes/family-policy.md, experiment 7).
    """
    n = plant.order
    gain = np.zeros(_W)
    gain[[*range(n), MAX_ORDER]] = frame.gain
    return np.concatenate([(np.arange(MAX_ORDER) < n).astype(float), np.arcsinh(gain)])


def _frame_rows(frame: CardFrame, width: int) -> dict[str, Tensor]:
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


class CardPlant(PlantPart):
    """The plant's code from its model card: a bank of descriptors (buffers), encoded by an MLP.

    ``hidden``: the encoder's width; ``duration``: the frame's step (:func:`card_frame`).
    """

    maps_states = True  #: the normaliser maps each plant's state into its card's frame

    cards: Tensor  #: (n_tags, CARD_FEATURES)
    card_mean: Tensor  #: the training rows' mean: the encoder reads ``(card - mean) / std``
    card_std: Tensor

    def __init__(self, dim: int, n_tags: int, hidden: int = 128, duration: float = 10.0) -> None:
        super().__init__()
        self.n_tags = require_int("model.plant.n_tags", n_tags)
        self.duration = require_nonnegative("model.plant.duration", duration)
        if self.duration == 0:
            raise ValueError("model.plant.duration must be > 0 (seconds of the scales' step)")
        width = require_int("model.plant.hidden", hidden)
        self.register_buffer("cards", torch.zeros(self.n_tags, CARD_FEATURES))
        self.register_buffer("card_mean", torch.zeros(CARD_FEATURES))
        self.register_buffer("card_std", torch.ones(CARD_FEATURES))
        self.encoder = nn.Sequential(
            nn.Linear(CARD_FEATURES, width), nn.ReLU(),
            nn.Linear(width, width), nn.ReLU(), nn.Linear(width, dim),
        )  # fmt: skip

    def forward(
        self, state: Tensor | None, mask: Tensor | None, ref: Tensor | None, tag: Tensor
    ) -> tuple[Tensor, None]:
        """The code (B, dim) of each row's card; nothing read from the window."""
        return self.encoder((self.cards[tag] - self.card_mean) / self.card_std), None

    def plant_rows(self, plants: Sequence[Plant], width: int) -> dict[str, Tensor]:
        """Each plant's card and its frame's normaliser rows (:func:`_frame_rows`), stacked."""
        rows: dict[str, list[Tensor]] = {}
        for p in plants:
            frame = card_frame(p, self.duration)
            features = torch.as_tensor(card_features(p, frame))[None]
            rows.setdefault("net.plant.cards", []).append(features)
            for k, v in _frame_rows(frame, width).items():
                rows.setdefault(k, []).append(v)
        return {k: torch.cat(v) for k, v in rows.items()}

    @torch.no_grad()
    def fit_plants(self, plants: Sequence[Plant]) -> None:
        """The training cards' mean and spread become the encoder's standardisation."""
        cards = self.cards[torch.as_tensor([p.tag for p in plants], dtype=torch.long)].double()
        self.card_mean.copy_(cards.mean(0))
        self.card_std.copy_(cards.std(0, unbiased=False).clamp(min=STD_FLOOR))
