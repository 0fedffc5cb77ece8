"""A one-tensor view of a :class:`~generalist_control.model.policy.Policy` for MLflow.

MLflow's PyTorch flavour and its model signature take one input array; :class:`FlatPolicy`
takes the window's state, mask and reference history and the tag as the columns of
:func:`flat_columns`.
"""

from __future__ import annotations

from torch import Tensor, nn

from generalist_control.model.policy import Policy

__all__ = ["FlatPolicy", "flat_columns"]


def flat_columns(history: int, state_dim: int) -> list[str]:
    """Column names of :class:`FlatPolicy`'s input (``k = 0`` is the oldest sample).

    ``state_dim`` is the state input's width (the padded plant state, then the channels of
    ``model.channels``: the error integral, the previous control).
    """
    cols = [f"state_{k}_{i}" for k in range(history) for i in range(state_dim)]
    cols += [f"mask_{k}_{i}" for k in range(history) for i in range(state_dim)]
    cols += [f"ref_{k}" for k in range(history)]
    return [*cols, "tag"]


class FlatPolicy(nn.Module):
    """One-tensor view of a :class:`Policy` for MLflow's PyTorch flavour.

    Input: float32 (B, 2 * history * width + history + 1) (``width``:
    :attr:`Policy.width <generalist_control.model.policy.Policy.width>`), columns
    :func:`flat_columns` (state, mask, reference, tag). Output: controls (B, horizon).
    """

    def __init__(self, policy: Policy) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, x: Tensor) -> Tensor:
        """Controls in plant units for flat rows ``x``."""
        T, n = self.policy.history, self.policy.width
        state = x[:, : T * n].reshape(-1, T, n)
        mask = x[:, T * n : 2 * T * n].reshape(-1, T, n)
        ref = x[:, 2 * T * n : 2 * T * n + T]
        tag = x[:, -1].round().long()
        return self.policy(state, mask, ref, tag)[0]
