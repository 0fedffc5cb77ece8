"""The network's building blocks (paper, Section 4): encoders, attention, experts."""

from __future__ import annotations

import math

from torch import Tensor, nn

__all__ = ["ExpertMLP", "SummaryAttention", "mlp"]


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
