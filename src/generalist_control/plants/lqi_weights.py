"""The LQI weights of a drawn plant: Bryson's rule at a drawn loop bandwidth ``w_c``.

``R = I``, ``Q = q_y C^T C + q_z I`` with ``q_y = 1 / |G(j w_c)|^2``, ``q_z = (ratio w_c)^2 q_y``:
the loop crosses over near ``w_c`` in any coordinates (docs/notes/plant-families.md).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from generalist_control.plants.definition import rhp_roots

__all__ = ["BrysonRule", "NoBandwidthError", "Weights", "right_half_plane"]


class NoBandwidthError(ValueError):
    """No bandwidth satisfies the rule's limits (an unstable pole too close to an RHP zero)."""


def right_half_plane(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[float, float]:
    """The largest real part of an unstable pole (0: none) and the smallest RHP zero (inf)."""
    poles, zeros = rhp_roots(A, B, C, 1e-8)  # integrators come out within ~1e-12 of 0
    return (float(poles.real.max()) if poles.size else 0.0), (
        float(np.abs(zeros).min()) if zeros.size else math.inf
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
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class BrysonRule:
    """Bryson's rule at a bandwidth drawn log-uniform in ``bandwidth`` (rad/s).

    The ratio ``w_i / w_c`` is drawn log-uniform in ``integral_ratio``; ``w_c`` lies at least
    ``margin`` times an unstable pole and at most an RHP zero over ``margin``.
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
