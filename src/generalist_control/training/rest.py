"""A training term that makes the policy's loop come to rest (``rest``, issue 13).

Imitation weighs an action error by its size, and near the set point every error is small:
a policy can match its experts there to the loss's precision and still close a loop that is
unstable in the small, so it never settles (the set-point check,
:mod:`generalist_control.evaluation.setpoint`, finds such plants). :class:`RestPenalty`
measures that loop during training and penalises it: at a random constant reference, each
sampled plant version's loop linearised at rest (:mod:`generalist_control.model.rest_loop`)
has eigenvalues ``lambda``; each above the target radius ``rho_t = 1 - slack (1 -
rho_LQI)`` (``rho_LQI``: the plant's own LQI loop sampled the same way) adds
``|lambda| - rho_t`` to the term. The loop matrix is ``A0 + b law^T`` with the policy's
window Jacobian in ``law`` (taken with ``create_graph``), and each eigenvalue's value is
the first-order expression ``v^H A u / v^H u`` with its left and right eigenvectors held
fixed, so its gradient is the eigenvalue's derivative with respect to the weights.

Nothing here comes from an expert's law but the target radius: the term asks the network's
own loop to be stable at rest, whatever its gains.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch.nn.attention import SDPBackend, sdpa_kernel

from generalist_control.model.rest_loop import (
    equilibrium,
    integral_at_rest,
    loop_parts,
    rest_window,
    window_law,
)
from generalist_control.plants.plant import MAX_ORDER, Plant
from generalist_control.simulation.lqi import design_lqi, sampled_closed_loop
from generalist_control.simulation.simulate import discretise

__all__ = ["RestPenalty"]

Window = tuple[Tensor, Tensor, Tensor, Tensor]


@dataclass(frozen=True)
class _Version:
    """One plant version's loop parts and its equilibrium per unit reference."""

    plant: Plant
    tag: int
    A0: Tensor
    b: Tensor
    x1: np.ndarray
    u1: float
    z1: float
    target: float


def _version(plant: Plant, tag: int, history: int, controls: bool, slack: float) -> _Version:
    """The loop parts of ``plant`` (window of ``history``), its rest per unit reference."""
    gains = design_lqi(plant)
    x1, u1, r = equilibrium(plant, 1.0)
    z1 = -(u1 + float(np.dot(gains.Kx, x1))) / float(gains.Ki)
    if r == 0.0:  # a nonlinear plant rests at its operating point whatever r asks
        x1, u1, z1 = np.zeros(plant.order), 0.0, 0.0
    Ad, Bd = discretise(plant.A, plant.B, plant.dt)
    A0, b = loop_parts(Ad, Bd, plant.C, plant.dt, history, True, controls)
    rho = float(np.abs(np.linalg.eigvals(sampled_closed_loop(plant, gains))).max())
    return _Version(plant, tag, torch.as_tensor(A0), torch.as_tensor(b), x1, u1, z1,
                    1.0 - slack * (1.0 - rho))  # fmt: skip


def _excess(A: Tensor, target: float) -> tuple[Tensor, float]:
    """``sum(|lambda| - target)`` over the eigenvalues above ``target``; the radius.

    Each such eigenvalue is ``v^T A u / v^T u`` with its right eigenvector ``u`` (of ``A``)
    and left one ``v`` (of ``A^T``, same eigenvalue) held fixed: its value, and to first
    order its derivative. Left and right eigenvectors are found apart, since the window's
    delay chain makes ``A`` defective at 0 (no inverse of the eigenvector matrix).
    """
    with torch.no_grad():
        lam, U = torch.linalg.eig(A)
        mu, V = torch.linalg.eig(A.T)
        radius = float(lam.abs().max())
        keep = torch.nonzero(lam.abs() > target).flatten()
        if len(keep) == 0:
            return A.new_zeros(()), radius
        match = (lam[keep, None] - mu[None, :]).abs().argmin(1)
        u, v = U[:, keep], V[:, match]
    Ac = A.to(U.dtype)
    lam_k = (v * (Ac @ u)).sum(0) / (v * u).sum(0)
    excess = (lam_k.abs() - target).clamp(min=0.0).sum()
    return (excess if torch.isfinite(excess) else A.new_zeros(())), radius


class RestPenalty:
    """The rest-stability term of the training loss (``rest`` config block).

    Parameters
    ----------
    plants : sequence of Plant
        The plant versions to hold stable at rest (the training plants and their variants).
    tags : mapping
        Plant name -> the policy's tag (variants take their plant's).
    history : int
        The window length (``data.history``).
    controls : bool
        The window carries the previous control (``model.control_history``).
    per_step : int
        Plant versions drawn (without replacement) each time the term is taken.
    reference : float
        References are uniform in ``+-reference * amplitude_scale`` (linear plants; a
        nonlinear plant rests at its operating point).
    slack : float
        The target radius is ``1 - slack * (1 - rho_LQI)``: 1 allows LQI's radius only,
        0 anything below 1.
    weight : float
        The term's weight in the loss.
    every : int
        Taken on every ``every``-th training batch.
    seed : int
    """

    def __init__(
        self,
        plants: Sequence[Plant],
        tags: Mapping[str, int],
        history: int,
        controls: bool,
        weight: float = 1.0,
        every: int = 1,
        per_step: int = 8,
        reference: float = 1.0,
        slack: float = 0.5,
        seed: int = 0,
    ) -> None:
        if not 0.0 <= slack <= 1.0:
            raise ValueError(f"rest.slack must lie in [0, 1], got {slack}")
        if per_step < 1 or every < 1:
            raise ValueError(f"rest.per_step and rest.every must be >= 1, got {per_step}, {every}")
        self.versions = [_version(p, int(tags[p.name]), history, controls, slack)
                         for p in plants]  # fmt: skip
        self.history, self.controls = int(history), bool(controls)
        self.per_step, self.reference = int(per_step), float(reference)
        self.weight, self.every = float(weight), int(every)
        self.rng = np.random.default_rng(seed)
        self.last_radius = float("nan")

    def _windows(self, chosen: list[_Version]) -> tuple[Window, Tensor, Tensor]:
        """The chosen versions' rest windows (at LQI's integral), ``u*`` and LQI's ``z``."""
        refs = self.rng.uniform(-1.0, 1.0, len(chosen)) * self.reference
        parts, u_star, z0 = [], [], []
        for v, s in zip(chosen, refs, strict=True):
            r = 0.0 if not v.plant.is_linear else float(s) * v.plant.amplitude_scale
            k = r if v.plant.is_linear else 0.0
            parts.append(rest_window(v.plant, k * v.x1, k * v.z1, k * v.u1, r,
                                     history=self.history, controls=self.controls,
                                     tag=v.tag))  # fmt: skip
            u_star.append(k * v.u1)
            z0.append(k * v.z1)
        state, mask, ref, tag = (torch.cat(c) for c in zip(*parts, strict=True))
        return (
            (state, mask, ref, tag),
            torch.tensor(u_star, dtype=torch.float64),
            torch.tensor(z0).double(),
        )

    def step(self, policy: torch.nn.Module, batch_idx: int) -> Tensor | None:
        """The weighted term for training batch ``batch_idx`` (None: not taken on it)."""
        if self.weight <= 0 or batch_idx % self.every:
            return None
        term = self(policy)
        return None if term is None else self.weight * term

    def __call__(self, policy: torch.nn.Module) -> Tensor | None:
        """The unweighted term (None: no drawn version has an equilibrium near LQI's)."""
        n = min(self.per_step, len(self.versions))
        chosen = [self.versions[i] for i in self.rng.choice(len(self.versions), n, False)]
        window, u_star, z0 = self._windows(chosen)
        dtype = next(policy.parameters()).dtype
        window = (window[0].to(dtype), window[1].to(dtype), window[2].to(dtype), window[3])
        was = policy.training
        policy.eval()
        try:
            width = torch.clamp(z0.abs(), min=1.0)
            z = integral_at_rest(policy, window, u_star, z0, width)
            ok = torch.isfinite(z)
            if not bool(ok.any()):
                return None
            state = window[0][ok].clone()
            state[..., MAX_ORDER] = z[ok][:, None].to(dtype)
            state.requires_grad_(True)
            with sdpa_kernel(SDPBackend.MATH):  # the CPU's fused attention has no 2nd derivative
                u, _ = policy(state, *(w[ok] for w in window[1:]))
            (jac,) = torch.autograd.grad(u[:, 0].sum(), state, create_graph=True)
        finally:
            policy.train(was)
        terms, radii = [], []
        kept = [c for c, k in zip(chosen, ok.tolist(), strict=True) if k]
        for v, J in zip(kept, jac, strict=True):
            n_x = v.plant.order
            ju = J[:, -1] if self.controls else None
            law = window_law(J[:, :n_x], J[:, MAX_ORDER], ju).double()
            term, radius = _excess(v.A0 + torch.outer(v.b, law), v.target)
            terms.append(term)
            radii.append(radius)
        self.last_radius = max(radii)
        return torch.stack(terms).mean().to(dtype)
