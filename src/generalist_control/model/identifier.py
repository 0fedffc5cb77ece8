"""The transition-set identifier: the plant read from the window's one-step transitions.

Each transition is encoded alone and averaged (DeepSets); optionally each plant's linear
one-step model weighs its evidence (docs/notes/transition-identifier.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

__all__ = ["TransitionModels", "TransitionSet"]


class TransitionSet(nn.Module):
    """``tanh(rho(mean_j phi(x_j, x_(j+1) - x_j, u_j, m)))`` over a window's transitions.

    ``u_j``: the last channel at ``j + 1``; ``m``: the order mask. ``models`` builds the
    plants' :class:`TransitionModels`, whose evidence follows the encoder's output.
    """

    def __init__(
        self,
        state_dim: int,
        hidden: int,
        models: Callable[..., TransitionModels] | None = None,
    ) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.models = None if models is None else models(state_dim=state_dim, embedding=hidden)
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

    def forward(self, state: Tensor, mask: Tensor, rows: Tensor | None = None) -> Tensor:
        """The state (B, hidden) of windows, then (with :attr:`models`) the plants' evidence."""
        if state.shape[1] < 2:
            raise ValueError("the transition identifier needs a window of at least 2 samples")
        steps = self.transitions(state, mask)
        code = torch.tanh(self.rho(self.phi(steps).mean(dim=1)))
        if self.models is None:
            return code
        if rows is None:
            raise ValueError("the transition models need the plants' embedding rows")
        n = self.state_dim
        x, dx, u = steps[..., :n], steps[..., n : 2 * n], steps[..., 2 * n]
        # the control that took sample j - 1 to j: the channel at sample j
        evidence = self.models(x, dx, u, rows, u_prev=state[:, :-1, -1])
        return torch.cat([code, evidence], dim=-1)

    def read(self, state: Tensor, mask: Tensor, rows: Tensor | None, noise: float = 0.0) -> Tensor:
        """The identifier's state of windows; with ``noise`` > 0, of noisy copies of them.

        White noise on the plant states, its std per window uniform in ``[0, noise]``.
        """
        if noise > 0:
            n = self.state_dim
            std = noise * torch.rand(state.shape[0], 1, 1, device=state.device, dtype=state.dtype)
            noisy = state[..., :n] + std * torch.randn_like(state[..., :n]) * mask[..., :n]
            state = torch.cat([noisy, state[..., n:]], dim=-1)
        return self(state, mask, rows)


class TransitionModels(nn.Module):
    """Each plant's linear one-step model ``theta_p = W e_p + w`` (zero at first), its evidence.

    ``eps`` is added to the residual (no motion: equal evidence); ``input_gain`` the fitted
    input gain's range (None: 1); ``lags`` the input lags tried; ``offset``: fit a constant
    input disturbance.
    """

    def __init__(
        self,
        state_dim: int,
        embedding: int,
        eps: float = 1e-6,
        input_gain: Sequence[float] | None = None,
        lags: Sequence[float] = (0.0,),
        offset: bool = False,
    ) -> None:
        super().__init__()
        self.state_dim, self.eps = state_dim, eps
        gain = None if input_gain is None else tuple(float(g) for g in input_gain)
        if gain is not None and not (len(gain) == 2 and 0 < gain[0] <= 1 <= gain[1]):
            raise ValueError(
                f"model.plant.identifier.models.input_gain must be a range [low, high] with "
                f"0 < low <= 1 <= high, or null; got {input_gain}"
            )
        if not lags or any(not 0.0 <= a <= 1.0 for a in lags):
            raise ValueError(
                "model.plant.identifier.models.lags must be a non-empty list of values in "
                f"[0, 1] ([0.0]: no lag), got {lags}"
            )
        self.input_gain = None if gain is None else (gain[0], gain[1])
        self.lags, self.offset = tuple(float(a) for a in lags), bool(offset)
        self.params = nn.Linear(embedding, state_dim * (state_dim + 2))
        nn.init.zeros_(self.params.weight)
        nn.init.zeros_(self.params.bias)

    def theta(self, rows: Tensor) -> Tensor:
        """Each plant's ``[A_p, b_p, c_p]`` (plants, state_dim, state_dim + 2)."""
        n = self.state_dim
        theta = self.params(rows)
        a = theta[:, : n * n].reshape(-1, n, n)
        return torch.cat([a, theta[:, n * n :].reshape(-1, 2, n).transpose(1, 2)], dim=2)

    def fit(
        self, x: Tensor, dx: Tensor, u: Tensor, rows: Tensor, u_prev: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Each plant's model fitted to the window's transitions, at its best gain, lag and offset.

        From the window's second moments in float64 (the sum cancels where a model fits); a
        fitted input in closed form. :attr:`lags` need ``u_prev``, the control one transition
        earlier.

        Returns
        -------
        residual, gain : Tensor
            The mean squared residual and the least-squares input gain (within
            :attr:`input_gain`, else 1), each (B, plants).
        """
        n = self.state_dim
        fitted_input = self.input_gain is not None or self.offset or self.lags != (0.0,)
        cols = [x, u.unsqueeze(-1), torch.ones_like(u).unsqueeze(-1)]
        if self.lags != (0.0,):
            if u_prev is None:
                raise ValueError("fitting an input lag needs u_prev, the control one step earlier")
            cols.append(u_prev.unsqueeze(-1))
        z = torch.cat(cols, dim=-1).double()
        dx, t = dx.double(), z.shape[1]
        s_zz = torch.einsum("btk,btl->bkl", z, z) / t
        s_zd = torch.einsum("btk,bti->bik", z, dx) / t
        theta = self.theta(rows).double()
        b = theta[:, :, n]
        extra = z.shape[-1] - (n + 2)  # the u_prev column: no model reads it directly
        theta = torch.cat([theta, theta.new_zeros(theta.shape[0], n, extra)], 2)
        if fitted_input:  # the model without its input column ...
            theta = torch.cat(
                [theta[:, :, :n], torch.zeros_like(b)[..., None], theta[:, :, n + 1 :]], 2
            )
        gram = torch.einsum("pik,pil->pkl", theta, theta).flatten(1)
        rss = (dx**2).sum(dim=(1, 2)).unsqueeze(1) / t - 2.0 * s_zd.flatten(1) @ theta.flatten(1).T
        rss = rss + s_zz.flatten(1) @ gram.T
        if not fitted_input:
            return rss.clamp(min=0.0).to(x.dtype), torch.ones_like(rss).to(x.dtype)
        fit, gain = self._fit_input(rss, s_zz, s_zd, theta, b)
        return fit.to(x.dtype), gain.to(x.dtype)

    def _fit_input(
        self, rss: Tensor, s_zz: Tensor, s_zd: Tensor, theta: Tensor, b: Tensor
    ) -> tuple[Tensor, Tensor]:
        """``b_p (g u_a + d)`` fitted to the residual ``rss`` of the model without column ``b``."""
        n = self.state_dim

        def mean_br(k: int) -> Tensor:  # mean over the window of (b_p . r) z_k, (B, plants)
            return s_zd[:, :, k] @ b.T - torch.einsum("pi,pik,bk->bp", b, theta, s_zz[:, :, k])

        lag = torch.tensor(self.lags, dtype=rss.dtype, device=rss.device).view(-1, 1, 1)
        bb = (b**2).sum(1)
        dv, suu, su = mean_br(n), s_zz[:, n, n].unsqueeze(1), s_zz[:, n, n + 1].unsqueeze(1)
        if s_zz.shape[-1] > n + 2:  # u_a = (1 - a) u + a u_prev, u_prev the last column
            last = n + 2
            dv = (1 - lag) * dv + lag * mean_br(last)
            suu = (1 - lag) ** 2 * suu + lag**2 * s_zz[:, last, last].unsqueeze(1)
            suu = suu + 2 * lag * (1 - lag) * s_zz[:, n, last].unsqueeze(1)
            su = (1 - lag) * su + lag * s_zz[:, last, n + 1].unsqueeze(1)
        else:
            dv, suu, su = dv.unsqueeze(0), suu.unsqueeze(0), su.unsqueeze(0)
        d1 = mean_br(n + 1) if self.offset else torch.zeros_like(rss)
        gain, offset = torch.ones_like(dv), torch.zeros_like(dv)
        if self.input_gain is not None:
            var = suu - su**2 if self.offset else suu  # the control's spread the gain fits
            cov = dv - su * d1 if self.offset else dv
            g = (cov / (var * bb).clamp(min=1e-300)).clamp(*self.input_gain)
            gain = torch.where(var * bb > 1e-12 * suu.clamp(min=1e-300) * bb, g, gain)
        if self.offset:  # the best offset for that gain (a convex quadratic: exact)
            offset = torch.where(bb > 0, d1 / bb.clamp(min=1e-300) - gain * su, offset)
        # g^2 (suu |b|^2) in this order, and the offset's terms added as exact zeros without
        # it: the gain-only fit keeps the bits of the models before the lag and the offset
        fit = rss - 2.0 * (gain * dv + offset * d1) + gain**2 * (suu * bb)
        fit = (fit + bb * (2.0 * gain * offset * su + offset**2)).clamp(min=0.0)
        best = fit.argmin(dim=0, keepdim=True)  # the lag that fits each model best
        return fit.gather(0, best)[0], gain.gather(0, best)[0]

    def forward(
        self, x: Tensor, dx: Tensor, u: Tensor, rows: Tensor, u_prev: Tensor | None = None
    ) -> Tensor:
        """Evidence ``-1/2 log(residual + eps)`` (B, plants) of each plant's model."""
        return -0.5 * torch.log(self.fit(x, dx, u, rows, u_prev)[0] + self.eps)

    def fit_loss(self, evidence: Tensor, tag: Tensor) -> Tensor:
        """``1/2 log(1 + residual / eps)`` of the true plant's model, over a batch (>= 0)."""
        true = evidence.gather(1, tag.unsqueeze(1)).squeeze(1)
        return (-true - 0.5 * torch.log(torch.tensor(self.eps))).mean()
