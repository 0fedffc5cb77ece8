"""The Generalist Controller network (paper, Section 4), composed from parts in ``conf/model``.

Encoders, a fast and a strided LSTM, attention, a gated mixture of experts; ours besides: the
plant part, a skip path, extra ``channels`` and per-window scaling (docs/training.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import cast

import torch
from torch import Tensor, nn

from generalist_control.common.sections import require_int, require_switch
from generalist_control.model.linear import LinearSkip
from generalist_control.model.plant import PlantPart, PlantReading
from generalist_control.plants.definition import MAX_ORDER

__all__ = [
    "CHANNELS",
    "WINDOW_SCALE_FLOOR",
    "ExpertMLP",
    "GeneralistNetwork",
    "NetOutput",
    "SummaryAttention",
    "count_parameters",
    "mlp",
]

#: The window's extra state channels, in order after the padded state.
CHANNELS = ("integral", "previous_control")

#: Smallest window scale (normalised units): a window at rest maps to inputs near zero.
WINDOW_SCALE_FLOOR = 1e-3

Part = Callable[..., nn.Module]


@dataclass(frozen=True)
class NetOutput:
    """One forward pass of :class:`~generalist_control.model.network.GeneralistNetwork`."""

    control: Tensor  #: (B, horizon), normalised units divided by the window scale
    gates: Tensor  #: (B, experts), the mixture's softmax weights
    scale: Tensor  #: (B, 1), each window's scale (ones without window scaling)
    plant: PlantReading | None  #: what an inferred plant part read (None: by its tag)


def mlp(n_in: int, n_hidden: int, n_out: int) -> nn.Sequential:
    """Two-layer encoder ``W_2 relu(W_1 x + b_1) + b_2`` (paper, Eq. f_1..f_4)."""
    return nn.Sequential(nn.Linear(n_in, n_hidden), nn.ReLU(), nn.Linear(n_hidden, n_out))


class SummaryAttention(nn.Module):
    """Multi-head attention with a residual, ``z + W_O [a_1 .. a_H]``, ``d_k = ceil(dim / heads)``.

    The one token is ``z``, so the softmax over one key is 1: :meth:`forward` computes
    ``z + W_O V z``. Q and K are kept for the paper's parameter count (zero gradient).
    """

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.d_k = math.ceil(dim / heads)
        inner = heads * self.d_k
        self.qkv = nn.Linear(dim, 3 * inner)
        self.out = nn.Linear(inner, dim)

    def forward(self, z: Tensor) -> Tensor:
        """The block's output for the one token ``z`` (B, dim): ``z + W_O V z`` (B, dim)."""
        inner = self.heads * self.d_k
        return z + self.out(self.qkv(z)[..., 2 * inner :])


class ExpertMLP(nn.Sequential):
    """One expert: three linear layers, ReLU then LayerNorm after each hidden layer."""

    def __init__(self, n_in: int, n_hidden: int, n_out: int) -> None:
        super().__init__(
            nn.Linear(n_in, n_hidden),
            nn.ReLU(),
            nn.LayerNorm(n_hidden),
            nn.Linear(n_hidden, n_hidden),
            nn.ReLU(),
            nn.LayerNorm(n_hidden),
            nn.Linear(n_hidden, n_out),
        )


def _channels(channels: Sequence[str]) -> tuple[str, ...]:
    """``model.channels`` checked: known names, each once, in the window's order."""
    if isinstance(channels, str) or not all(isinstance(c, str) for c in channels):
        raise ValueError(f"model.channels must be a list of names, got {channels!r}")
    unknown = [c for c in channels if c not in CHANNELS]
    if unknown:
        raise ValueError(f"model.channels: unknown {unknown}; known: {list(CHANNELS)}")
    if len(set(channels)) != len(channels):
        raise ValueError(f"model.channels names a channel twice: {list(channels)}")
    return tuple(c for c in CHANNELS if c in channels)


class GeneralistNetwork(nn.Module):
    """The network of the paper on *normalised* inputs (docs/training.md).

    Parameters
    ----------
    plant, skip : callable
        Build the plant part (``plant(dim=hidden)``) and the optional skip path.
    hidden, heads, stride, experts, history, horizon : int
        ``d`` (even), ``N_h``, ``tau``, ``M``, ``T_h`` and ``K``.
    channels : sequence of str
        Extra state channels of the window (:data:`CHANNELS`), after the padded state.
    law_history : int, optional
        The newest samples the law reads (the plant part reads the whole window); None: all.
    window_scale : bool
        Divide each window by its peak and return the scale (:attr:`NetOutput.scale`).

    Examples
    --------
    >>> from functools import partial
    >>> from generalist_control.model.plant import TagEmbedding
    >>> net = GeneralistNetwork(partial(TagEmbedding, n_tags=25), hidden=32, experts=3)
    >>> out = net(torch.zeros(5, 8, 5), torch.ones(5, 8, 5), torch.zeros(5, 8),
    ...           torch.zeros(5, dtype=torch.long))
    >>> tuple(out.control.shape), tuple(out.gates.shape)
    ((5, 3), (5, 3))
    """

    def __init__(
        self,
        plant: Part,
        hidden: int = 32,
        heads: int = 3,
        stride: int = 2,
        experts: int = 3,
        history: int = 8,
        horizon: int = 3,
        skip: Part | None = None,
        channels: Sequence[str] = ("integral",),
        law_history: int | None = None,
        window_scale: bool = True,
    ) -> None:
        super().__init__()
        d = require_int("model.hidden", hidden)
        if d % 2:
            raise ValueError(f"model.hidden must be even (encoders give hidden // 2), got {d}")
        e = d // 2
        self.history = require_int("data.history", history)
        self.horizon = require_int("data.horizon", horizon)
        self.n_experts = require_int("experts", experts)
        self.stride = require_int("model.stride", stride)
        self.channels = _channels(channels)
        self.window_scale = bool(require_switch("model.window_scale", window_scale))
        self.state_dim = state_dim = MAX_ORDER
        self.law_history = self._law_history(law_history)
        self.width = state_dim + len(self.channels)
        self.law_width = law_width = state_dim + ("integral" in self.channels)  # [x; z]
        self.state_encoder_1 = mlp(law_width, d, e)
        self.state_encoder_2 = mlp(law_width, d, e)
        self.ref_encoder = mlp(1, d, e)
        self.plant = cast(PlantPart, plant(dim=d))
        self.n_tags = int(self.plant.n_tags)  #: system tags ``0 .. n_tags - 1``
        missing = [c for c in self.plant.needs if c not in self.channels]
        if missing:
            raise ValueError(
                f"model.plant ({type(self.plant).__name__}) reads the window's {missing} "
                f"channel: add it to model.channels (now {list(self.channels)})"
            )
        self.plant_encoder = nn.Sequential(nn.ReLU(), nn.Linear(d, e))
        self.lstm_fast = nn.LSTM(4 * e, d, batch_first=True)
        self.lstm_slow = nn.LSTM(4 * e, d, batch_first=True)
        self.attention = SummaryAttention(2 * d, require_int("model.heads", heads))
        self.experts = nn.ModuleList(
            ExpertMLP(2 * d, d, self.horizon) for _ in range(self.n_experts)
        )
        self.gate = nn.Linear(2 * d, self.n_experts)
        sizes = {"horizon": self.horizon, "width": law_width, "history": self.law_history}
        summary = 2 * d + self.plant.summary_size
        self.skip = (
            None if skip is None else cast(LinearSkip, skip(dim=d, summary=summary, **sizes))
        )
        # the slow LSTM sees samples ..., t - 2 tau, t - tau, t (always the newest one)
        self.slow_start = (self.law_history - 1) % self.stride

    def _law_history(self, law_history: int | None) -> int:
        """``model.law_history`` checked against the window (None: the whole window)."""
        if law_history is None:
            return self.history
        n = require_int("model.law_history", law_history)
        if n > self.history:
            raise ValueError(
                f"model.law_history ({n}) exceeds the window (data.history = {self.history}):"
                " lower it, or lengthen data.history"
            )
        return n

    def scaled_inputs(self, state: Tensor, ref: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Each window divided by its peak (at least :data:`WINDOW_SCALE_FLOOR`), and the peaks.

        The LQI law is linear, so scaled step responses of every amplitude coincide.
        """
        if not self.window_scale:
            return state, ref, torch.ones_like(ref[:, :1])
        peak = torch.maximum(state.abs().amax(dim=(1, 2)), ref.abs().amax(dim=1))
        s = peak.clamp(min=WINDOW_SCALE_FLOOR).unsqueeze(1)
        return state / s.unsqueeze(2), ref / s, s

    def forward(self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor) -> NetOutput:
        """The output for normalised windows: state, mask (B, history, width), ref, tag."""
        state, ref, scale = self.scaled_inputs(state, ref)
        code, reading = self.plant(state, mask, ref, tag)
        n = self.law_history  # the law reads the newest n samples only
        # the paper's X * M without the previous-control channel: [x; z] per step
        x, ref = (state[:, -n:] * mask[:, -n:])[..., : self.law_width], ref[:, -n:]
        f_plant = self.plant_encoder(code).unsqueeze(1).expand(-1, n, -1)
        f = torch.cat(
            [self.state_encoder_1(x), self.state_encoder_2(x), self.ref_encoder(ref[..., None]),
             f_plant],
            dim=-1,
        )  # fmt: skip
        _, (h_fast, _) = self.lstm_fast(f)
        _, (h_slow, _) = self.lstm_slow(f[:, self.slow_start :: self.stride])
        z = torch.cat([h_fast[-1], h_slow[-1]], dim=-1)
        z_att = self.attention(z)
        gates = torch.softmax(self.gate(z_att), dim=-1)
        u_experts = torch.stack([expert(z_att) for expert in self.experts], dim=1)
        u = torch.einsum("bm,bmk->bk", gates, u_experts)
        if self.skip is not None:
            summary = z_att if reading is None else torch.cat([z_att, reading.summary], -1)
            u = u + self.skip(code, x, ref, summary)
        return NetOutput(control=u, gates=gates, scale=scale, plant=reading)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
