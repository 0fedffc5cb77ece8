"""Linear paths added to the experts' output (ours, ``model.skip``) on the newest samples.

With the error integral the LQI law is linear in the newest ``[x; z]``: such a path can carry
the feedback exactly and leave the experts the rest.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from generalist_control.common.sections import require_int, require_nonnegative

__all__ = ["ContextSkip", "LinearSkip", "linear_features"]


def linear_features(state: Tensor, ref: Tensor, samples: int) -> Tensor:
    """The newest ``samples`` of the state ``[x; z]`` (B, T, w), flattened, then of ``ref``."""
    return torch.cat([state[:, -samples:].flatten(1), ref[:, -samples:]], dim=1)


def _samples(key: str, samples: int, history: int) -> int:
    """``samples`` checked: at most the law's ``history``."""
    n = require_int(key, samples)
    if n > history:
        raise ValueError(
            f"{key} ({n}) exceeds the samples the law reads ({history}: model.law_history or "
            "data.history): lower it"
        )
    return n


class LinearSkip(nn.Module):
    """``u += G(code) w``, gains ``G = A code + b`` (zero at first), ``w`` the newest ``samples``.

    The sizes are given by the network (``summary``: read by :class:`ContextSkip` only).
    """

    def __init__(
        self, dim: int, horizon: int, width: int, history: int, summary: int = 0, samples: int = 1
    ) -> None:
        super().__init__()
        self.samples = _samples("model.skip.samples", samples, history)
        self.horizon = horizon
        self.gains = nn.Linear(dim, horizon * self.samples * (width + 1))
        nn.init.zeros_(self.gains.weight)
        nn.init.zeros_(self.gains.bias)

    def gain_input(self, code: Tensor, summary: Tensor) -> Tensor:
        """What the gains are computed from: the plant's code."""
        return code

    def scaled(self, gains: Tensor, source: Tensor) -> Tensor:
        """The gains as they are applied (unscaled here)."""
        return gains

    def forward(self, code: Tensor, state: Tensor, ref: Tensor, summary: Tensor) -> Tensor:
        """The path's controls (B, horizon) for the law's window ``state``, ``ref``."""
        window = linear_features(state, ref, self.samples)
        source = self.gain_input(code, summary)
        gains = self.scaled(self.gains(source).view(-1, self.horizon, window.shape[1]), source)
        return torch.einsum("bkf,bf->bk", gains, window)


class ContextSkip(LinearSkip):
    """A :class:`LinearSkip` whose gains also read the window's summary, scaled by ``exp(s)``.

    ``s = gain_range tanh(s' / gain_range)``, ``s'`` learned (zero at first): the gains span
    a factor ``e^gain_range``, as LQI's do across plants.
    """

    def __init__(
        self,
        dim: int,
        horizon: int,
        width: int,
        history: int,
        summary: int,
        samples: int = 1,
        gain_range: float = 6.0,
    ) -> None:
        super().__init__(dim, horizon, width, history, summary, samples)
        self.gain_range = require_nonnegative("model.skip.gain_range", gain_range)
        if self.gain_range == 0:
            raise ValueError("model.skip.gain_range must be > 0 (use a linear skip instead)")
        self.scale = nn.Linear(dim, 1)
        nn.init.zeros_(self.scale.weight)
        nn.init.zeros_(self.scale.bias)
        self.context = nn.Linear(summary, dim)

    def gain_input(self, code: Tensor, summary: Tensor) -> Tensor:
        """The plant's code plus a projection of the window's summary."""
        return code + self.context(summary)

    def scaled(self, gains: Tensor, source: Tensor) -> Tensor:
        """The gains times ``exp(s)`` (:attr:`gain_range`)."""
        exponent = self.gain_range * torch.tanh(self.scale(source) / self.gain_range)
        return gains * torch.exp(exponent).unsqueeze(-1)
