"""The network's building blocks (paper, Section 4): encoders, attention, experts."""

from __future__ import annotations

import math

import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["ExpertMLP", "SummaryAttention", "mlp"]


def mlp(n_in: int, n_hidden: int, n_out: int) -> nn.Sequential:
    """Two-layer encoder ``W_2 relu(W_1 x + b_1) + b_2`` (paper, Eq. f_1..f_4)."""
    return nn.Sequential(nn.Linear(n_in, n_hidden), nn.ReLU(), nn.Linear(n_hidden, n_out))


class SummaryAttention(nn.Module):
    """Multi-head scaled dot-product attention with a residual: ``z + W_O [a_1 .. a_H]``.

    Parameters
    ----------
    dim : int
        Token size (``2 d_h`` in the paper).
    heads : int
        ``N_h``. Each head has ``d_k = ceil(dim / heads)``; the concatenated heads
        (``heads * d_k``, which may exceed ``dim``) are projected back to ``dim`` by ``W_O``.

    Notes
    -----
    As in the paper the tokens are the temporal summary ``z`` alone (one token per window),
    so the softmax over a single key is identically one and the block computes
    ``z + W_O V z``: with one token that is what :meth:`forward` computes, to the bit what
    the attention gives, without its kernel (a tenth of a training step). The query and
    key projections are kept for fidelity with the paper (and its parameter count); they
    receive zero gradient.
    """

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.d_k = math.ceil(dim / heads)
        inner = heads * self.d_k
        self.qkv = nn.Linear(dim, 3 * inner)
        self.out = nn.Linear(inner, dim)

    def forward(self, tokens: Tensor) -> Tensor:
        """Attend over ``tokens`` (B, T, dim); return the same shape."""
        B, T, _ = tokens.shape
        inner = self.heads * self.d_k
        if T == 1:  # one key: every head's weights are one, its output is its value
            return tokens + self.out(self.qkv(tokens)[..., 2 * inner :])
        qkv = self.qkv(tokens).view(B, T, 3, self.heads, self.d_k).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])  # (B, heads, T, d_k)
        return tokens + self.out(a.transpose(1, 2).reshape(B, T, self.heads * self.d_k))


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
