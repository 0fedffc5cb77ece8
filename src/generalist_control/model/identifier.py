"""The transition-set identifier (``model.transition_identifier``, issue 13).

Reads the plant from the window's one-step transitions ``(x_j, u_j, x_(j+1) - x_j)``, each
encoded alone by a shared MLP and averaged over the window (a DeepSets encoder, Zaheer et
al. 2017), then mapped to the identifier's state. A transition depends on the plant only,
not on the controller that chose ``u_j``; an LSTM over the window can also learn the shape
of the expert's closed loop, which the policy's own loop does not reproduce. The average is
over every transition of the window, so a few odd samples move it little; a longer window
(``data.history``, the law reading only the newest ``model.law_history``) holds more.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["TransitionSet"]


class TransitionSet(nn.Module):
    """``tanh(rho(mean_j phi(x_j, x_(j+1) - x_j, u_j, m)))`` over a window's transitions.

    Parameters
    ----------
    state_dim : int
        Padded plant state entries at the front of each sample (``MAX_ORDER``).
    hidden : int
        Size of ``phi``'s layers and of the output.

    Notes
    -----
    The window's last channel is the control applied one sample earlier
    (``model.control_history``), so the control that took sample ``j`` to ``j + 1`` is that
    channel at ``j + 1``. ``m`` is the plant's order mask (padding and the mask carry the
    order). Samples the history repeats before the first one give ``x_(j+1) = x_j`` under
    the control 0: seen identically in training and at run time (the one window builder).

    Examples
    --------
    >>> enc = TransitionSet(state_dim=4, hidden=8)
    >>> tuple(enc(torch.zeros(2, 5, 6), torch.ones(2, 5, 6)).shape)
    (2, 8)
    """

    def __init__(self, state_dim: int, hidden: int) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.phi = nn.Sequential(
            nn.Linear(3 * state_dim + 1, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
        )
        self.rho = nn.Linear(hidden, hidden)

    def transitions(self, state: Tensor, mask: Tensor) -> Tensor:
        """Inputs of ``phi`` (B, history - 1, 3 state_dim + 1) of a masked window."""
        n = self.state_dim
        x = (state * mask)[..., :n]
        u = state[:, 1:, -1:]
        order = mask[:, 1:, :n]
        return torch.cat([x[:, :-1], x[:, 1:] - x[:, :-1], u, order], dim=-1)

    def forward(self, state: Tensor, mask: Tensor) -> Tensor:
        """The identifier's state (B, hidden) of windows (B, history, width)."""
        if state.shape[1] < 2:
            raise ValueError("the transition identifier needs a window of at least 2 samples")
        return torch.tanh(self.rho(self.phi(self.transitions(state, mask)).mean(dim=1)))
