"""Conditions a controller was not trained for, applied inside the closed loop.

:class:`Perturbation` is one run's; :class:`RowPerturbations` applies every run's to its rows
of one stacked loop (:func:`~generalist_control.simulation.simulate.simulate_stacked`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Perturbation", "RowPerturbations"]


@dataclass(frozen=True)
class Perturbation:
    """Conditions the controller was not trained for, applied inside the loop.

    Amplitude and rate (per second) limits; white state noise (``noise_std`` per entry, or
    (n, n): a square root of its covariance; from ``noise_start``, seeded); an input
    disturbance from ``disturbance_start``; the plant receives ``actuator_gain`` times the
    delivered (recorded) control.
    """

    u_limit: float | None = None
    rate_limit: float | None = None
    noise_std: float | tuple[float, ...] | tuple[tuple[float, ...], ...] | None = None
    noise_start: float = 0.0
    disturbance: float = 0.0
    disturbance_start: float = 0.0
    actuator_gain: float = 1.0
    seed: int = 0

    def noise(self, z: np.ndarray) -> np.ndarray:
        """The state noise of standard normal draws ``z`` (..., n)."""
        std = np.asarray(self.noise_std, dtype=float)
        return z @ std.T if std.ndim == 2 else z * np.broadcast_to(std, z.shape[-1:])

    def actuate(self, u_cmd: np.ndarray, u_prev: np.ndarray, dt: float) -> np.ndarray:
        """The control the actuator delivers for command ``u_cmd`` after ``u_prev``."""
        u = u_cmd
        if self.rate_limit is not None:
            du = self.rate_limit * dt
            u = np.clip(u, u_prev - du, u_prev + du)
        if self.u_limit is not None:
            u = np.clip(u, -self.u_limit, self.u_limit)
        return u


class RowPerturbations:
    """Every run's :class:`Perturbation` applied to its rows of one loop, as it applies alone."""

    def __init__(
        self, runs: Sequence[tuple[slice, Perturbation | None, int, int]], steps: int, dt: float
    ) -> None:
        """``runs``: per run its rows, perturbation (or None), plant order and length."""
        rate, clip, gain, dist, noise = [], [], [], [], []
        for rows, p, order, length in runs:
            idx = np.arange(rows.start, rows.stop)
            if p is None:
                continue
            if p.rate_limit is not None:
                rate.append((idx, p.rate_limit * dt))
            if p.u_limit is not None:
                clip.append((idx, p.u_limit))
            if p.actuator_gain != 1.0:
                gain.append((idx, p.actuator_gain))
            if p.disturbance:
                k0 = _first(p.disturbance_start, dt, steps)
                dist.append((idx, np.full(idx.size, p.disturbance), k0))
            if p.noise_std is not None:  # one draw: the numbers of one draw per sample
                k0 = _first(p.noise_start, dt, steps)
                z = np.random.default_rng(p.seed).normal(
                    size=(max(length - k0, 0), idx.size, order)
                )
                noise.append((rows, p.noise(z), k0))
        self.rate, self.clip, self.gain = _stack(rate), _stack(clip), _stack(gain)
        self.dist, self.noise = dist, noise
        self.prev = np.zeros(max((r[0].stop for r in runs), default=0))

    def measure(self, x: np.ndarray, k: int) -> np.ndarray:
        """The states the controllers see at sample ``k``: ``x`` plus any noise due."""
        due = [(rows, z[k - k0]) for rows, z, k0 in self.noise if k0 <= k < k0 + len(z)]
        if not due:
            return x
        xm = x.copy()
        for rows, z in due:
            n = z.shape[1]
            xm[rows, :n] = x[rows, :n] + z
        return xm

    def actuate(self, u: np.ndarray) -> np.ndarray:
        """Rate limit, then amplitude limit (in place); the rate limit remembers the result."""
        if self.rate is not None:
            idx, du = self.rate
            prev = self.prev[idx]
            u[idx] = np.clip(u[idx], prev - du, prev + du)
        if self.clip is not None:
            idx, lim = self.clip
            u[idx] = np.clip(u[idx], -lim, lim)
        if self.rate is not None:
            self.prev[self.rate[0]] = u[self.rate[0]]
        return u

    def applied(self, u: np.ndarray, k: int) -> np.ndarray:
        """What the plants receive: the delivered ``u`` times any gain, plus any disturbance."""
        due = [(i, v) for i, v, k0 in self.dist if k >= k0]
        if self.gain is None and not due:
            return u
        ua = u.copy()
        if self.gain is not None:
            idx, g = self.gain
            ua[idx] = u[idx] * g
        for idx, v in due:
            ua[idx] = ua[idx] + v
        return ua


def _first(start: float, dt: float, steps: int) -> int:
    """The first sample ``k`` with ``k * dt >= start`` (as the simulator tests it)."""
    return next((k for k in range(steps) if k * dt >= start), steps)


def _stack(parts: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray] | None:
    if not parts:
        return None
    idx = np.concatenate([i for i, _ in parts])
    return idx, np.concatenate([np.full(i.size, v) for i, v in parts])
