"""One SISO plant, linear or nonlinear about an operating point, immutable.

Everything outside this module works in deviation coordinates about the operating point.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

__all__ = [
    "MAX_ORDER",
    "Plant",
    "PlantConfigError",
    "Signal",
    "linearise",
    "pad_states",
    "rhp_roots",
]

#: Largest plant order the policy handles (states are zero-padded to this length).
MAX_ORDER = 4

Dynamics = Callable[..., np.ndarray]


class PlantConfigError(ValueError):
    """A plant's configuration is invalid; the message names the plant and the field."""


@dataclass(frozen=True)
class Signal:
    """Name and unit of one state, input or output signal."""

    name: str
    unit: str


@dataclass(frozen=True, eq=False)
class Plant:
    """One SISO plant with its LQI weights ``Q`` (on ``[x; z]``) and ``R``.

    ``A, B, C`` are the model or its linearisation at the operating point; ``f(x, u,
    **params)`` and ``h(x, **params)`` (None for linear plants) work in absolute
    coordinates, batched; ``amplitude_scale`` scales the data's step amplitudes.
    """

    name: str
    tag: int
    description: str
    source: str
    states: tuple[Signal, ...]
    input_signal: Signal
    output_signal: Signal
    dt: float
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    f: Dynamics | None = None
    h: Dynamics | None = None
    params: Mapping[str, float] = field(default_factory=dict)
    x_op: np.ndarray | None = None
    u_op: float = 0.0
    y_op: float = 0.0
    substeps: int = 10
    amplitude_scale: float = 1.0

    @property
    def order(self) -> int:
        """Number of states ``n``."""
        return self.A.shape[0]

    @property
    def is_linear(self) -> bool:
        """True when the plant is simulated with its linear model."""
        return self.f is None

    def deriv(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """State derivative for state deviations ``x`` (batch, n) and inputs ``u`` (batch,)."""
        if self.f is None:
            return x @ self.A.T + u[:, None] * self.B[:, 0]
        return self.f(x + self.x_op, u + self.u_op, **self.params)

    def output(self, x: np.ndarray) -> np.ndarray:
        """Output deviation ``y - y_op`` for a batch of state deviations ``(batch, n)``."""
        if self.h is None:
            return x @ self.C[0]
        return self.h(x + self.x_op, **self.params) - self.y_op


def pad_states(x: np.ndarray) -> np.ndarray:
    """Zero-pad the last axis of ``x`` (..., n) to ``MAX_ORDER``."""
    n = x.shape[-1]
    if n > MAX_ORDER:
        raise ValueError(f"state has {n} entries; at most {MAX_ORDER} are supported")
    out = np.zeros((*x.shape[:-1], MAX_ORDER), dtype=x.dtype)
    out[..., :n] = x
    return out


def rhp_roots(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, rel_tol: float
) -> tuple[np.ndarray, np.ndarray]:
    """Poles and zeros with a real part above ``rel_tol * max(1, max |A|)``.

    Zeros are the finite generalised eigenvalues of ``[[A, B], [C, 0]]`` (square systems).
    """
    n = A.shape[0]
    scale = max(1.0, float(np.abs(A).max()))
    poles = np.linalg.eigvals(A)
    system = np.block([[A, B], [C, np.zeros((C.shape[0], B.shape[1]))]])
    pencil = np.zeros_like(system)
    pencil[:n, :n] = np.eye(n)
    zeros = scipy.linalg.eigvals(system, pencil)
    zeros = zeros[np.isfinite(zeros) & (np.abs(zeros) < 1e8 * scale)]
    tol = rel_tol * scale
    return poles[poles.real > tol], zeros[zeros.real > tol]


def linearise(
    f: Dynamics, h: Dynamics | None, x_op: np.ndarray, u_op: float, params: Mapping[str, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Jacobians of ``f`` (and ``h``) at the operating point by central differences.

    Returns
    -------
    A, B, C : ndarray
        ``df/dx`` (n x n), ``df/du`` (n x 1) and ``dh/dx`` (1 x n, ``None`` without ``h``).
    """
    n = x_op.shape[0]
    eps = 1e-6 * np.maximum(1.0, np.abs(np.append(x_op, u_op)))
    xs = np.tile(x_op, (2 * n + 2, 1))
    us = np.full(2 * n + 2, float(u_op))
    for i in range(n):
        xs[2 * i, i] += eps[i]
        xs[2 * i + 1, i] -= eps[i]
    us[2 * n] += eps[n]
    us[2 * n + 1] -= eps[n]
    fx = f(xs, us, **params)
    d = (fx[0::2] - fx[1::2]) / (2 * eps[:, None])
    A, B = d[:n].T, d[n:].T
    C = None
    if h is not None:
        hx = h(xs[: 2 * n], **params)
        C = ((hx[0::2] - hx[1::2]) / (2 * eps[:n]))[None, :]
    return A, B, C
