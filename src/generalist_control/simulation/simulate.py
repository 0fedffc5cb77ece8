"""Closed-loop simulation of a plant under any controller, vectorised over runs.

Linear plants advance by the exact zero-order hold, nonlinear ones by RK4; ``u[k]`` is held.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.linalg import expm

from generalist_control.plants.definition import Plant, pad_states

__all__ = [
    "BatchController",
    "Controller",
    "PerPlantController",
    "Perturbation",
    "Run",
    "Trajectory",
    "discretise",
    "plant_stepper",
    "rk4",
    "row_slices",
    "simulate",
    "simulate_many",
]

#: A state whose magnitude exceeds this is treated as diverged.
DIVERGENCE_BOUND = 1e6


class Controller(Protocol):
    """What the simulator drives: batched, stateful, one call per sample."""

    def reset(self, batch_size: int) -> None:
        """Clear internal state before ``batch_size`` parallel runs."""

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls ``(batch,)`` for states ``(batch, n)`` and references ``(batch,)``."""


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


@dataclass(frozen=True)
class Trajectory:
    """A batch of closed-loop runs in deviation coordinates: ``x`` (batch, N + 1, n), ``y``.

    ``u`` (batch, N) is the delivered control (before any disturbance); a ``diverged`` run
    (non-finite or beyond ``DIVERGENCE_BOUND``) is frozen at its last finite state.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    r: np.ndarray
    y: np.ndarray
    diverged: np.ndarray


def discretise(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation via the block matrix exponential (cached)."""
    A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
    Ad, Bd = _discretise(A.tobytes(), B.tobytes(), B.shape, float(dt))
    return Ad.copy(), Bd.copy()


@functools.lru_cache(maxsize=512)
def _discretise(
    a: bytes, b: bytes, shape: tuple[int, int], dt: float
) -> tuple[np.ndarray, np.ndarray]:
    n, m = shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = np.frombuffer(a).reshape(n, n)
    M[:n, n:] = np.frombuffer(b).reshape(n, m)
    E = expm(M * dt)
    return E[:n, :n], E[:n, n:]


def rk4(
    deriv: Callable[[np.ndarray], np.ndarray], x: np.ndarray, h: float, substeps: int
) -> np.ndarray:
    """``substeps`` classic Runge-Kutta steps of length ``h`` of ``dx/dt = deriv(x)``."""
    for _ in range(substeps):
        k1 = deriv(x)
        k2 = deriv(x + 0.5 * h * k1)
        k3 = deriv(x + 0.5 * h * k2)
        k4 = deriv(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


class _Group:
    """The state of a batch of runs on one plant while the loop advances."""

    def __init__(
        self, plant: Plant, r: np.ndarray, x0: np.ndarray | None, pert: Perturbation | None
    ) -> None:
        r = np.atleast_2d(np.asarray(r, dtype=float))
        self.plant, self.r, self.pert = plant, r, pert
        self.batch, self.steps = r.shape
        n = plant.order
        self.x = np.zeros((self.batch, self.steps + 1, n))
        if x0 is not None:
            x0 = np.asarray(x0, dtype=float)
            if x0.shape != (self.batch, n):
                raise ValueError(
                    f"x0 has shape {x0.shape}; plant '{plant.name}' needs ({self.batch}, {n})"
                )
            self.x[:, 0] = x0
        self.u = np.zeros((self.batch, self.steps))
        self.u_prev = np.zeros(self.batch)
        self.diverged = np.zeros(self.batch, dtype=bool)
        self.rng = np.random.default_rng(pert.seed) if pert is not None else None
        if plant.is_linear:
            self.Ad, self.Bd = discretise(plant.A, plant.B, plant.dt)

    def _advance(self, xk: np.ndarray, uk: np.ndarray) -> np.ndarray:
        """One sample of the unperturbed plant."""
        p = self.plant
        if p.is_linear:
            return xk @ self.Ad.T + uk[:, None] * self.Bd[:, 0]
        return rk4(lambda x: p.deriv(x, uk), xk, p.dt / p.substeps, p.substeps)

    def measure(self, k: int) -> np.ndarray:
        """The state the controller sees at sample ``k`` (with noise, if any)."""
        xm, pert = self.x[:, k], self.pert
        if (
            pert is not None
            and self.rng is not None
            and pert.noise_std is not None
            and k * self.plant.dt >= pert.noise_start
        ):
            xm = xm + pert.noise(self.rng.normal(size=xm.shape))
        return xm

    def apply(self, k: int, u_cmd: np.ndarray) -> None:
        """Pass the command through the actuator and advance one sample."""
        uk = np.asarray(u_cmd, dtype=float).reshape(self.batch)
        pert = self.pert
        if pert is not None:
            uk = pert.actuate(uk, self.u_prev, self.plant.dt)
            self.u_prev = uk
        self.u[:, k] = uk
        if pert is not None and pert.actuator_gain != 1.0:
            uk = uk * pert.actuator_gain
        if pert is not None and pert.disturbance and k * self.plant.dt >= pert.disturbance_start:
            uk = uk + pert.disturbance
        nxt = self._advance(self.x[:, k], uk)
        bad = ~np.all(np.isfinite(nxt) & (np.abs(nxt) < DIVERGENCE_BOUND), axis=1)
        self.diverged |= bad
        self.x[:, k + 1] = np.where(self.diverged[:, None], self.x[:, k], nxt)

    def result(self) -> Trajectory:
        """The runs as a :class:`Trajectory`."""
        n = self.plant.order
        y = self.plant.output(self.x.reshape(-1, n)).reshape(self.batch, self.steps + 1)
        t = np.arange(self.steps + 1) * self.plant.dt
        return Trajectory(t=t, x=self.x, u=self.u, r=self.r, y=y, diverged=self.diverged)


def plant_stepper(plant: Plant) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``advance(x, u) -> x_next``: the simulator's unperturbed sample of ``plant``, batched."""
    return _Group(plant, np.zeros((1, 1)), None, None)._advance


def simulate(
    plant: Plant,
    controller: Controller,
    r: np.ndarray,
    x0: np.ndarray | None = None,
    perturbation: Perturbation | None = None,
) -> Trajectory:
    """Simulate ``controller`` on ``plant`` for references ``r`` (batch, N) from ``x0`` or rest."""
    g = _Group(plant, r, x0, perturbation)
    controller.reset(g.batch)
    with np.errstate(all="ignore"):
        for k in range(g.steps):
            g.apply(k, controller.step(g.measure(k), g.r[:, k]))
    return g.result()


@dataclass(frozen=True)
class Run:
    """A batch of runs on one plant for :func:`simulate_many`."""

    plant: Plant
    r: np.ndarray
    x0: np.ndarray | None = None
    perturbation: Perturbation | None = None


class BatchController(Protocol):
    """A controller of many plants at once (the learned policy, or LQI experts stacked)."""

    def reset(self, plants: Sequence[Plant], counts: Sequence[int]) -> None:
        """Prepare for ``counts[i]`` runs of ``plants[i]``, stacked in that order."""

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls ``(B,)`` for zero-padded states ``(B, MAX_ORDER)`` and references."""


def simulate_many(runs: Sequence[Run], controller: BatchController) -> list[Trajectory]:
    """Simulate runs on several plants in lockstep, one controller call per sample.

    All runs must share the sample time and the number of samples. Rows are stacked in the
    order of ``runs``; states reach the controller zero-padded to ``MAX_ORDER``.
    """
    groups = [_Group(run.plant, run.r, run.x0, run.perturbation) for run in runs]
    if len({g.steps for g in groups}) != 1 or len({g.plant.dt for g in groups}) != 1:
        raise ValueError("simulate_many needs runs of equal length and sample time")
    controller.reset([g.plant for g in groups], [g.batch for g in groups])
    splits = np.cumsum([g.batch for g in groups])[:-1]
    with np.errstate(all="ignore"):
        for k in range(groups[0].steps):
            x = np.concatenate([pad_states(g.measure(k)) for g in groups])
            r = np.concatenate([g.r[:, k] for g in groups])
            u = np.asarray(controller.step(x, r), dtype=float)
            for g, uk in zip(groups, np.split(u, splits), strict=True):
                g.apply(k, uk)
    return [g.result() for g in groups]


def row_slices(counts: Sequence[int]) -> list[slice]:
    """The rows of each group when ``counts[i]`` runs of group ``i`` are stacked in order."""
    ends = np.cumsum([0, *counts])
    return [slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:], strict=True)]


class PerPlantController:
    """A :class:`BatchController` of one ``make(plant)`` controller per group of rows."""

    def __init__(self, make: Callable[[Plant], Controller]) -> None:
        self.make = make
        self._parts: list[tuple[Controller, int, slice]] = []

    def reset(self, plants: Sequence[Plant], counts: Sequence[int]) -> None:
        """Build and reset one controller per plant."""
        self._parts = []
        for plant, count, rows in zip(plants, counts, row_slices(counts), strict=True):
            ctrl = self.make(plant)
            ctrl.reset(count)
            self._parts.append((ctrl, plant.order, rows))

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Route each group's rows (unpadded) to its controller."""
        u = np.empty(x.shape[0])
        for ctrl, n, rows in self._parts:
            u[rows] = ctrl.step(x[rows, :n], r[rows])
        return u
