"""A one-tensor view of a policy for MLflow, whose PyTorch flavour takes one input array."""

from __future__ import annotations

from torch import Tensor, nn

from generalist_control.model.policy import Policy

__all__ = ["FlatPolicy", "flat_columns"]


def flat_columns(history: int, state_dim: int) -> list[str]:
    """Column names of :class:`FlatPolicy`'s input (``k = 0``: the oldest sample)."""
    cols = [f"state_{k}_{i}" for k in range(history) for i in range(state_dim)]
    cols += [f"mask_{k}_{i}" for k in range(history) for i in range(state_dim)]
    cols += [f"ref_{k}" for k in range(history)]
    return [*cols, "tag"]


class FlatPolicy(nn.Module):
    """Input float32 (B, 2 T width + T + 1) in :func:`flat_columns`; output (B, horizon)."""

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
