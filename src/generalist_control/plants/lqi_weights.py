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

__all__ = ["BrysonRule", "NoBandwidthError", "Weights", "bounds", "log_uniform"]


class NoBandwidthError(ValueError):
    """No bandwidth satisfies the rule's limits (an unstable pole too close to an RHP zero)."""


def log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    """A draw log-uniform in ``bounds``."""
    return float(np.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1]))))


def bounds(name: str, value: Any) -> tuple[float, float]:
    """``families.generator.<name>`` as ``(low, high)``: finite, ``0 < low <= high``."""
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"families.generator.{name} must be [low, high], got {value!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise ValueError(
            f"families.generator.{name} = [{lo}, {hi}] must be finite with low <= high and low > 0"
        )
    return lo, hi


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
            object.__setattr__(self, key, bounds(f"weights.{key}", getattr(self, key)))
        if not 1.0 <= float(self.margin) < math.inf:
            raise ValueError("families.generator.weights.margin must be a number >= 1")

    def band(self, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[float, float]:
        """The bandwidths the plant allows within ``bandwidth``.

        Raises
        ------
        NoBandwidthError
            If none is left, naming the pole and the zero.
        """
        poles, zeros = rhp_roots(A, B, C, 1e-8)  # integrators come out within ~1e-12 of 0
        p = float(poles.real.max()) if poles.size else 0.0  # the largest unstable pole
        z = float(np.abs(zeros).min()) if zeros.size else math.inf  # the smallest RHP zero
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
        w = log_uniform(rng, (lo, hi))
        ratio = float(np.exp(rng.uniform(*np.log(self.integral_ratio))))
        G = C @ np.linalg.solve(1j * w * np.eye(A.shape[0]) - A, B)
        q_y = 1.0 / float(np.linalg.norm(G, 2)) ** 2
        return Weights(w, ratio, q_y, (ratio * w) ** 2 * q_y)
