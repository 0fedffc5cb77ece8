"""The policy's loop at rest, linearised: shared by the set-point check and its training term.

At the equilibrium of a constant reference ``r`` a plant rests at ``x*`` under ``u*``
(:func:`equilibrium`), and a policy with the error integral holds it there at the integral
``z*`` where its control is ``u*`` (:func:`integral_at_rest`). With every sample of the
window at that equilibrium (:func:`rest_window`, built by the one window builder), the
derivative of the policy's first control with respect to every window entry closes a linear
loop with the plant sampled at ``dt`` (:func:`closed_loop_matrix`): the state is the window
(the newest plant states, error integrals ``z_(k+1) = z_k + dt (r - C x_k)`` as the runtime
keeps them, and previous controls with the ``previous_control`` channel). Its spectral radius is
below 1 exactly when small deviations from rest die out.

The matrix is ``A0 + b law^T``: ``A0`` and ``b`` depend on the plant and the window's
layout only (:func:`loop_parts`), and the policy enters through ``law``, its Jacobian
arranged on the loop's state (:func:`window_law`), linearly, so the radius can be
differentiated with respect to the network's weights (``training.rest``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from generalist_control.data.windows import HistoryBuffer
from generalist_control.plants.plant import MAX_ORDER, Plant
from generalist_control.simulation.simulate import discretise

__all__ = [
    "closed_loop_matrix",
    "equilibrium",
    "integral_at_rest",
    "loop_parts",
    "rest_window",
    "window_law",
]


def equilibrium(plant: Plant, reference: float) -> tuple[np.ndarray, float, float]:
    """``(x*, u*, r)``: the plant at rest on ``reference`` (deviations; nonlinear: ``r = 0``).

    For a linear plant ``(Ad - I) x* + Bd u* = 0`` and ``C x* = r``; a nonlinear plant rests
    at its operating point (its linearisation's origin).

    Raises
    ------
    ValueError
        If a linear plant has no unique equilibrium for the reference (a zero at s = 0).
    """
    n = plant.order
    if not plant.is_linear:
        return np.zeros(n), 0.0, 0.0
    Ad, Bd = discretise(plant.A, plant.B, plant.dt)
    M = np.block([[Ad - np.eye(n), Bd.reshape(n, 1)], [plant.C.reshape(1, n), np.zeros((1, 1))]])
    try:
        sol = np.linalg.solve(M, np.r_[np.zeros(n), float(reference)])
    except np.linalg.LinAlgError as exc:
        raise ValueError(f"{plant.name}: no unique equilibrium for r = {reference}") from exc
    return sol[:n], float(sol[n]), float(reference)


def rest_window(
    plant: Plant,
    x: np.ndarray,
    z: float,
    u: float,
    r: float,
    *,
    history: int,
    controls: bool,
    tag: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The window after one sample ``(x, z, u_prev = u)`` at reference ``r``: float64, batch 1.

    Built by the one window builder (:class:`HistoryBuffer`, with the error integral), which
    repeats a first sample over the whole history, as at rest. ``tag``: the policy's tag for
    the plant.
    """
    buffer = HistoryBuffer(np.array([plant.order]), history, True, controls)
    padded = np.zeros((1, MAX_ORDER))
    padded[0, : plant.order] = x
    state, mask, ref = buffer.push(padded, np.array([r]), np.array([z]), np.array([u]))
    f64 = torch.float64
    return (torch.tensor(state, dtype=f64), torch.tensor(mask, dtype=f64),
            torch.tensor(ref, dtype=f64), torch.tensor([tag]))  # fmt: skip


@torch.no_grad()
def integral_at_rest(
    policy: torch.nn.Module,
    window: tuple[Tensor, Tensor, Tensor, Tensor],
    u_star: Tensor,
    z0: Tensor,
    width: Tensor,
    points: int = 201,
) -> Tensor:
    """Per window, the error integral nearest ``z0`` where the first control is ``u_star``.

    Batched and approximate, for training: the control is tabulated on ``points`` integrals
    within ``+-width`` of ``z0`` (every sample of the window's integral channel set alike)
    and the sign change of ``u - u_star`` nearest ``z0`` is interpolated linearly. NaN
    where there is none. ``window``: ``(state, mask, ref, tag)`` of ``B`` windows;
    ``u_star``, ``z0``, ``width``: (B,).
    """
    state, mask, ref, tag = window
    B, P = state.shape[0], points
    grid = z0[:, None] + width[:, None] * torch.linspace(-1.0, 1.0, P, dtype=z0.dtype)
    batch = state[:, None].repeat(1, P, 1, 1)
    batch[..., MAX_ORDER] = grid[..., None].to(batch.dtype)
    flat = (batch.reshape(B * P, *state.shape[1:]), mask.repeat_interleave(P, 0),
            ref.repeat_interleave(P, 0), tag.repeat_interleave(P, 0))  # fmt: skip
    u, _ = policy(*flat)
    resid = u[:, 0].reshape(B, P).to(grid.dtype) - u_star[:, None]
    flips = (torch.sign(resid[:, :-1]) * torch.sign(resid[:, 1:])) <= 0
    mid = 0.5 * (grid[:, :-1] + grid[:, 1:])
    dist = torch.where(flips, (mid - z0[:, None]).abs(), torch.full_like(mid, torch.inf))
    i = dist.argmin(1, keepdim=True)
    r0, r1 = resid.gather(1, i)[:, 0], resid.gather(1, i + 1)[:, 0]
    g0, g1 = grid.gather(1, i)[:, 0], grid.gather(1, i + 1)[:, 0]
    t = torch.where(r1 != r0, r0 / (r0 - r1), torch.full_like(r0, 0.5)).clamp(0.0, 1.0)
    z = g0 + t * (g1 - g0)
    return torch.where(torch.isfinite(dist.gather(1, i)[:, 0]), z, torch.nan)


def loop_parts(
    Ad: np.ndarray, Bd: np.ndarray, C: np.ndarray, dt: float, H: int, z: bool, u: bool
) -> tuple[np.ndarray, np.ndarray]:
    """``(A0, b)`` of the loop ``A0 + b law^T`` of a sampled plant and a window law.

    State, newest first: ``x_k .. x_(k-H+1)``, then ``z_k ..`` (``z``), then
    ``u_(k-1) ..`` (``u``). ``A0``: ``x_(k+1) = Ad x_k + Bd u_k``,
    ``z_(k+1) = z_k - dt C x_k``, the window shifts; ``b``: where ``u_k`` enters (``Bd`` on
    ``x_(k+1)``, 1 on the newest previous control).
    """
    n = Ad.shape[0]
    blocks = [n] + [1] * z + [1] * u
    offsets = np.cumsum([0] + [H * s for s in blocks])
    N = int(offsets[-1])
    A0, b = np.zeros((N, N)), np.zeros(N)

    def idx(block: int, j: int) -> slice:  # sample k-j of a block
        s = blocks[block]
        return slice(offsets[block] + j * s, offsets[block] + (j + 1) * s)

    A0[idx(0, 0), idx(0, 0)] = Ad
    b[idx(0, 0)] = Bd.reshape(n)
    if z:
        A0[idx(1, 0), idx(1, 0)] = 1.0
        A0[idx(1, 0), idx(0, 0)] = -dt * C.reshape(n)
    if u:
        b[idx(len(blocks) - 1, 0)] = 1.0
    for block, s in enumerate(blocks):
        for j in range(1, H):
            A0[idx(block, j), idx(block, j - 1)] = np.eye(s)
    return A0, b


def window_law(jx: Tensor, jz: Tensor | None, ju: Tensor | None) -> Tensor:
    """The law ``u_k = law . state`` on :func:`loop_parts`' state, from the window Jacobian.

    ``jx`` (H, n), ``jz`` (H,) and ``ju`` (H,): the control's derivative with respect to
    each window sample, oldest first (None: no such channel). Differentiable.
    """
    parts = [jx.flip(0).reshape(-1)] + [c.flip(0) for c in (jz, ju) if c is not None]
    return torch.cat(parts)


def closed_loop_matrix(
    Ad: np.ndarray,
    Bd: np.ndarray,
    C: np.ndarray,
    dt: float,
    jx: np.ndarray,
    jz: np.ndarray | None,
    ju: np.ndarray | None,
) -> np.ndarray:
    """The linear loop of a sampled plant and a window law, on the window's samples.

    ``jx`` (H, n), ``jz`` (H,) and ``ju`` (H,): the control's derivative with respect to
    each window sample, oldest first (``jz``/``ju`` None: no such channel). State, newest
    first: ``x_k .. x_(k-H+1)``, then ``z_k ..``, then ``u_(k-1) ..``. Steps:
    ``u_k = sum_j jx[-1-j] x_(k-j) + ...``, ``x_(k+1) = Ad x_k + Bd u_k``,
    ``z_(k+1) = z_k - dt C x_k``, and the previous control becomes ``u_k``.
    """
    A0, b = loop_parts(Ad, Bd, C, dt, jx.shape[0], jz is not None, ju is not None)

    def tensor(a: np.ndarray | None) -> Tensor | None:
        return None if a is None else torch.as_tensor(np.asarray(a, dtype=float))

    law = window_law(torch.as_tensor(np.asarray(jx, dtype=float)), tensor(jz), tensor(ju))
    return A0 + np.outer(b, law.numpy())
