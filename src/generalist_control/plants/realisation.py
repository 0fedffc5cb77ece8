"""A drawn transfer function in drawn state coordinates (:data:`FORMS`) and units."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["FORMS", "TransferModel", "realise", "scaled"]

#: A chain of first/second-order stages of DC gain 1, the companion form, the chain rotated.
FORMS = ("cascade", "companion", "rotated")


@dataclass(frozen=True)
class TransferModel:
    """``gain`` (``s^m G(s)`` at 0), poles (a complex pair once), real zeros, classes."""

    gain: float
    poles: tuple[complex, ...]
    zeros: tuple[float, ...]
    classes: tuple[str, ...]

    @property
    def order(self) -> int:
        """Number of states: a complex pair counts twice."""
        return sum(2 if p.imag > 0 else 1 for p in self.poles)

    def record(self) -> dict[str, Any]:
        """JSON-ready: gain, poles as ``[re, im]``, zeros, classes."""
        return {
            "gain": self.gain,
            "poles": [[p.real, p.imag] for p in self.poles],
            "zeros": list(self.zeros),
            "classes": list(self.classes),
        }


def _sections(model: TransferModel, rng: np.random.Generator) -> list[tuple[np.ndarray, ...]]:
    """The chain's stages, input first: ``(num, den)`` each of DC gain 1 (or 1/s)."""
    dens = []
    for p in model.poles:
        if p.imag > 0:
            w2 = abs(p) ** 2
            dens.append((np.array([w2]), np.array([1.0, -2 * p.real, w2])))
        else:
            dens.append((np.array([1.0 if p == 0 else -p.real]), np.array([1.0, -p.real])))
    order = rng.permutation(len(dens))
    stages = [list(dens[i]) for i in order]
    for z in model.zeros:  # into the first stage with room; the last stays strictly proper
        for k, (num, den) in enumerate(stages):
            room = len(den) - len(num) - (1 if k == len(stages) - 1 else 0)
            if room > 0:
                stages[k][0] = np.polymul(num, [-1.0 / z, 1.0])
                break
    stages[0][0] = stages[0][0] * model.gain
    return [(num, den) for num, den in stages]


def _stage(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, ...]:
    """Controllable canonical form ``(A, B, C, D)`` of ``num/den`` (monic ``den``)."""
    k = len(den) - 1
    b = np.zeros(k + 1)
    b[k + 1 - len(num) :] = num
    a, b = den[::-1][:k], b[::-1]  # ascending powers
    A = np.zeros((k, k))
    A[:-1, 1:] = np.eye(k - 1)
    A[-1] = -a
    B = np.zeros((k, 1))
    B[-1, 0] = 1.0
    C = (b[:k] - b[k] * a)[None, :]
    return A, B, C, np.array([[b[k]]])


def realise(
    model: TransferModel, form: str, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A, B, C)`` of ``model`` in :data:`FORMS` ``form`` (``rng`` orders the stages)."""
    stages = _sections(model, rng)
    if form == "companion":
        num, den = np.array([1.0]), np.array([1.0])
        for n_, d_ in stages:
            num, den = np.polymul(num, n_), np.polymul(den, d_)
        A, B, C, _ = _stage(num, den)
        return A, B, C
    A, B, C, D = _stage(*stages[0])
    for num, den in stages[1:]:  # in series: the next stage is driven by this one's output
        A2, B2, C2, D2 = _stage(num, den)
        A = np.block([[A, np.zeros((A.shape[0], A2.shape[0]))], [B2 @ C, A2]])
        B, C, D = np.vstack([B, B2 @ D]), np.hstack([D2 @ C, C2]), D2 @ D
    if form == "rotated":
        T, r = np.linalg.qr(rng.standard_normal((A.shape[0], A.shape[0])))
        T = T * np.sign(np.diag(r))
        A, B, C = T @ A @ T.T, T @ B, C @ T.T
    return A, B, C


def scaled(
    A: np.ndarray,
    B: np.ndarray,
    C: np.ndarray,
    w: float,
    units: tuple[float, float],
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States in drawn units: at ``w`` rad/s state ``i`` moves ``10^U`` times the output."""
    n = A.shape[0]
    x = np.linalg.solve(1j * w * np.eye(n) - A, B)[:, 0]
    y = complex((C @ x)[0])
    rel = np.abs(x / y)
    lo, hi = math.log(units[0]), math.log(units[1])
    scale = np.exp(rng.uniform(lo, hi, size=n)) / np.maximum(rel, 1e-300)
    return scale[:, None] * A / scale[None, :], scale[:, None] * B, C / scale[None, :]
