r"""The LQI weights of a drawn plant: Bryson's rule at a drawn loop bandwidth.

Bryson's rule weighs each signal by the inverse square of its acceptable size: an output
error ``y_max``; the input that moves the output by ``y_max`` at the loop's bandwidth
``w_c``, ``u_max = y_max / |G(j w_c)|``; the integral of an error ``y_max`` held for
``1 / w_i`` seconds, ``w_i = ratio * w_c``. Divided by the input's weight,

.. math:: R = I, \quad Q = q_y C^T C \oplus q_z I, \quad
   q_y = 1 / \|G(j w_c)\|^2, \quad q_z = w_i^2 q_y,

so the LQ loop crosses over near ``w_c`` (the symmetric root locus) whatever the plant's gain
and time scale, and the design does not depend on the state coordinates. ``w_c`` and the
ratio are drawn log-uniform (a user's weights are their own), ``w_c`` within the limits a
right-half-plane pole ``p`` and zero ``z`` set: ``margin * p <= w_c <= z / margin``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

__all__ = ["BrysonRule", "NoBandwidthError", "Weights", "right_half_plane"]


class NoBandwidthError(ValueError):
    """No bandwidth satisfies the rule's limits (an unstable pole too close to an RHP zero)."""


def right_half_plane(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[float, float]:
    """The largest real part of an unstable pole (0: none) and the smallest RHP zero (inf).

    Zeros are the finite generalised eigenvalues of ``[[A, B], [C, 0]]`` (square systems).
    """
    n = A.shape[0]
    scale = max(1.0, float(np.abs(A).max()))
    tol = 1e-8 * scale  # integrators come out within ~1e-12 of 0 in any coordinates
    poles = np.linalg.eigvals(A)
    system = np.block([[A, B], [C, np.zeros((C.shape[0], B.shape[1]))]])
    pencil = np.zeros_like(system)
    pencil[:n, :n] = np.eye(n)
    zeros = scipy.linalg.eigvals(system, pencil)
    zeros = zeros[np.isfinite(zeros) & (np.abs(zeros) < 1e8 * scale)]
    unstable = poles.real[poles.real > tol]
    rhp = np.abs(zeros[zeros.real > tol])
    return (float(unstable.max()) if unstable.size else 0.0), (
        float(rhp.min()) if rhp.size else math.inf
    )


@dataclass(frozen=True)
class Weights:
    """The drawn bandwidth ``w_c`` (rad/s), integral ratio and the weights they give."""

    bandwidth: float
    integral_ratio: float
    q_y: float
    q_z: float

    def matrices(self, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``Q`` on ``[x; z]`` (``n + outputs`` square) and ``R = I`` (``inputs`` square)."""
        p, n = C.shape
        Q = np.zeros((n + p, n + p))
        Q[:n, :n] = self.q_y * C.T @ C
        Q[n:, n:] = self.q_z * np.eye(p)
        return Q, np.eye(B.shape[1])

    def record(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "bandwidth": self.bandwidth,
            "integral_ratio": self.integral_ratio,
            "q_y": self.q_y,
            "q_z": self.q_z,
        }


@dataclass(frozen=True)
class BrysonRule:
    """Bryson's rule at a drawn bandwidth (module docstring); every field from config.

    Parameters
    ----------
    bandwidth : [low, high]
        Range of ``w_c`` in rad/s (log-uniform).
    integral_ratio : [low, high]
        Range of ``w_i / w_c`` (log-uniform).
    margin : float
        ``w_c`` at least ``margin`` times an unstable pole, at most an RHP zero over it.
    """

    bandwidth: tuple[float, float]
    integral_ratio: tuple[float, float]
    margin: float

    def __post_init__(self) -> None:
        for key in ("bandwidth", "integral_ratio"):
            lo, hi = (float(v) for v in getattr(self, key))
            if not (0 < lo <= hi < math.inf):
                raise ValueError(
                    f"families.generator.weights.{key} must be [low, high], 0 < low <= high"
                )
            object.__setattr__(self, key, (lo, hi))
        if not 1.0 <= float(self.margin) < math.inf:
            raise ValueError("families.generator.weights.margin must be a number >= 1")

    def band(self, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[float, float]:
        """The bandwidths the plant allows within ``bandwidth``.

        Raises
        ------
        NoBandwidthError
            If none is left, naming the pole and the zero.
        """
        p, z = right_half_plane(A, B, C)
        lo = max(self.bandwidth[0], self.margin * p)
        hi = min(self.bandwidth[1], z / self.margin)
        if lo > hi:
            raise NoBandwidthError(
                f"no loop bandwidth in {list(self.bandwidth)} rad/s lies between {self.margin:g} "
                f"x its unstable pole ({p:.4g}) and its RHP zero ({z:.4g}) / {self.margin:g}"
            )
        return lo, hi

    def draw(
        self, A: np.ndarray, B: np.ndarray, C: np.ndarray, rng: np.random.Generator
    ) -> Weights:
        """Draw ``w_c`` and the ratio; the weights the rule gives the plant ``(A, B, C)``."""
        lo, hi = self.band(A, B, C)
        w = float(np.exp(rng.uniform(math.log(lo), math.log(hi))))
        ratio = float(np.exp(rng.uniform(*np.log(self.integral_ratio))))
        G = C @ np.linalg.solve(1j * w * np.eye(A.shape[0]) - A, B)
        q_y = 1.0 / float(np.linalg.norm(G, 2)) ** 2
        return Weights(w, ratio, q_y, (ratio * w) ** 2 * q_y)
