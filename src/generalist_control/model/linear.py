"""Linear paths added to the experts' output (ours, ``model.skip``) on the newest samples.

With the error integral the LQI law is linear in the newest ``[x; z]``: such a path can carry
the feedback exactly and leave the experts the rest.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from generalist_control.common.sections import require_int, require_nonnegative

__all__ = ["ContextSkip", "LinearSkip"]


class LinearSkip(nn.Module):
    """``u += G(code) w``, gains ``G = A code + b`` (zero at first), ``w`` the newest ``samples``.

    ``w``: the newest ``samples`` of the state ``[x; z]``, flattened, then of ``ref``. The sizes
    are given by the network (``summary``: read by :class:`ContextSkip` only).
    """

    def __init__(
        self, dim: int, horizon: int, width: int, history: int, summary: int = 0, samples: int = 1
    ) -> None:
        super().__init__()
        self.samples = require_int("model.skip.samples", samples)
        if self.samples > history:
            raise ValueError(
                f"model.skip.samples ({self.samples}) exceeds the samples the law reads "
                f"({history}: model.law_history or data.history): lower it"
            )
        self.horizon, self.features = horizon, self.samples * (width + 1)
        self.gains = nn.Linear(dim, horizon * self.features)
        nn.init.zeros_(self.gains.weight)
        nn.init.zeros_(self.gains.bias)

    def gain_rows(self, code: Tensor, summary: Tensor) -> Tensor:
        """The gains (B, horizon, window), computed from the plant's code."""
        return self.gains(code).view(-1, self.horizon, self.features)

    def forward(self, code: Tensor, state: Tensor, ref: Tensor, summary: Tensor) -> Tensor:
        """The path's controls (B, horizon) for the law's window ``state``, ``ref``."""
        n = self.samples
        window = torch.cat([state[:, -n:].flatten(1), ref[:, -n:]], dim=1)
        return torch.einsum("bkf,bf->bk", self.gain_rows(code, summary), window)


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

    def gain_rows(self, code: Tensor, summary: Tensor) -> Tensor:
        """The gains from the code plus a projection of the summary, times ``exp(s)``."""
        source = code + self.context(summary)
        exponent = self.gain_range * torch.tanh(self.scale(source) / self.gain_range)
        gains = self.gains(source).view(-1, self.horizon, self.features)
        return gains * torch.exp(exponent).unsqueeze(-1)
