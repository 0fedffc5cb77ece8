"""The policy's loop at rest, linearised, for the set-point check (``evaluation/setpoint.py``).

Its spectral radius is below 1 exactly when small deviations from rest die out.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from generalist_control.data.windows import HistoryBuffer
from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.simulate import discretise

__all__ = ["closed_loop_matrix", "equilibrium", "rest_window"]


def equilibrium(plant: Plant, reference: float) -> tuple[np.ndarray, float, float]:
    """``(x*, u*, r)``: the plant at rest on ``reference`` (nonlinear: at its operating point).

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
    """The window (float64, batch 1) after one sample ``(x, z, u_prev = u)``: all at rest."""
    buffer = HistoryBuffer(np.array([plant.order]), history, True, controls)
    padded = np.zeros((1, MAX_ORDER))
    padded[0, : plant.order] = x
    state, mask, ref = buffer.push(padded, np.array([r]), np.array([z]), np.array([u]))
    f64 = torch.float64
    return (torch.tensor(state, dtype=f64), torch.tensor(mask, dtype=f64),
            torch.tensor(ref, dtype=f64), torch.tensor([tag]))  # fmt: skip


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

    ``jx`` (H, n), ``jz`` and ``ju`` (H,; None: no such channel): the control's derivative
    with respect to each window sample, oldest first. State, newest first: ``x_k ..``, then
    ``z_k ..``, then ``u_(k-1) ..``.
    """
    H, n = len(jx), Ad.shape[0]
    blocks = [n] + [1] * (jz is not None) + [1] * (ju is not None)
    offsets = np.cumsum([0] + [H * s for s in blocks])
    A0, b = np.zeros((offsets[-1], offsets[-1])), np.zeros(offsets[-1])

    def idx(block: int, j: int) -> slice:  # sample k-j of a block
        s = blocks[block]
        return slice(offsets[block] + j * s, offsets[block] + (j + 1) * s)

    A0[idx(0, 0), idx(0, 0)] = Ad
    b[idx(0, 0)] = Bd.reshape(n)
    if jz is not None:
        A0[idx(1, 0), idx(1, 0)] = 1.0
        A0[idx(1, 0), idx(0, 0)] = -dt * C.reshape(n)
    if ju is not None:
        b[idx(len(blocks) - 1, 0)] = 1.0
    for block, s in enumerate(blocks):
        for j in range(1, H):
            A0[idx(block, j), idx(block, j - 1)] = np.eye(s)
    parts = [np.asarray(jx, dtype=float)[::-1].reshape(-1)]
    parts += [np.asarray(c, dtype=float)[::-1] for c in (jz, ju) if c is not None]
    return A0 + np.outer(b, np.concatenate(parts))
