"""Closed-loop simulation of a plant under any controller, vectorised over runs.

Linear plants are advanced with the exact zero-order-hold discretisation of ``(A, B)``;
nonlinear plants with fixed-step RK4 using ``plant.substeps`` sub-steps per sample. The
controller is sampled every ``plant.dt``: at sample ``k`` it sees the state ``x[k]`` and the
reference ``r[k]`` and returns ``u[k]``, held constant until ``k + 1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
from scipy.linalg import expm

if TYPE_CHECKING:
    from generalist_control.plants import Plant

__all__ = ["Controller", "Perturbation", "Trajectory", "discretise", "simulate"]

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

    Attributes
    ----------
    u_limit : float, optional
        Actuator amplitude saturation ``|u| <= u_limit``.
    rate_limit : float, optional
        Actuator rate saturation ``|du/dt| <= rate_limit`` (per second).
    noise_std : float or sequence of float, optional
        Standard deviation of white noise added to the measured state (per state entry),
        from ``noise_start`` seconds on.
    disturbance : float
        Constant input disturbance added to the applied control from ``disturbance_start``.
    seed : int
        Seed of the noise generator (same seed, same noise).
    """

    u_limit: float | None = None
    rate_limit: float | None = None
    noise_std: float | tuple[float, ...] | None = None
    noise_start: float = 0.0
    disturbance: float = 0.0
    disturbance_start: float = 0.0
    seed: int = 0

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
    """A batch of closed-loop runs, in deviation coordinates.

    Attributes
    ----------
    t : ndarray, shape (N + 1,)
    x : ndarray, shape (batch, N + 1, n)
    u, r : ndarray, shape (batch, N)
        Control delivered by the actuator (after any saturation, before any input
        disturbance) and reference, over each sample interval.
    y : ndarray, shape (batch, N + 1)
    diverged : ndarray of bool, shape (batch,)
        Runs whose state became non-finite or exceeded ``DIVERGENCE_BOUND``; their
        trajectories are frozen at the last finite state.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    r: np.ndarray
    y: np.ndarray
    diverged: np.ndarray


def discretise(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation via the block matrix exponential."""
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, B
    E = expm(M * dt)
    return E[:n, :n], E[:n, n:]


def simulate(
    plant: Plant,
    controller: Controller,
    r: np.ndarray,
    x0: np.ndarray | None = None,
    perturbation: Perturbation | None = None,
) -> Trajectory:
    """Simulate ``controller`` on ``plant`` for references ``r``.

    Parameters
    ----------
    plant : Plant
    controller : Controller
    r : ndarray, shape (batch, N)
        Reference deviation at each sample.
    x0 : ndarray, shape (batch, n), optional
        Initial state deviation; rest (zeros) by default.
    perturbation : Perturbation, optional
        Actuator limits, measurement noise and input disturbance.

    Returns
    -------
    Trajectory
    """
    r = np.atleast_2d(np.asarray(r, dtype=float))
    batch, steps = r.shape
    n = plant.order
    x = np.zeros((batch, steps + 1, n))
    if x0 is not None:
        x0 = np.asarray(x0, dtype=float)
        if x0.shape != (batch, n):
            raise ValueError(f"x0 has shape {x0.shape}; plant '{plant.name}' needs ({batch}, {n})")
        x[:, 0] = x0
    u = np.zeros((batch, steps))
    diverged = np.zeros(batch, dtype=bool)
    controller.reset(batch)
    pert = perturbation
    rng = np.random.default_rng(pert.seed) if pert is not None else None
    u_prev = np.zeros(batch)
    if plant.is_linear:
        Ad, Bd = discretise(plant.A, plant.B, plant.dt)
        advance = lambda xk, uk: xk @ Ad.T + uk[:, None] * Bd[:, 0]  # noqa: E731
    else:
        h = plant.dt / plant.substeps

        def advance(xk: np.ndarray, uk: np.ndarray) -> np.ndarray:
            for _ in range(plant.substeps):
                k1 = plant.deriv(xk, uk)
                k2 = plant.deriv(xk + 0.5 * h * k1, uk)
                k3 = plant.deriv(xk + 0.5 * h * k2, uk)
                k4 = plant.deriv(xk + h * k3, uk)
                xk = xk + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
            return xk

    with np.errstate(all="ignore"):
        for k in range(steps):
            xm = x[:, k]
            if (
                pert is not None
                and pert.noise_std is not None
                and k * plant.dt >= pert.noise_start
            ):
                xm = xm + rng.normal(size=xm.shape) * np.broadcast_to(pert.noise_std, (n,))
            uk = np.asarray(controller.step(xm, r[:, k]), dtype=float).reshape(batch)
            if pert is not None:
                uk = pert.actuate(uk, u_prev, plant.dt)
                u_prev = uk
            u[:, k] = uk
            if pert is not None and pert.disturbance and k * plant.dt >= pert.disturbance_start:
                uk = uk + pert.disturbance
            nxt = advance(x[:, k], uk)
            bad = ~np.all(np.isfinite(nxt) & (np.abs(nxt) < DIVERGENCE_BOUND), axis=1)
            diverged |= bad
            x[:, k + 1] = np.where(diverged[:, None], x[:, k], nxt)
    y = plant.output(x.reshape(-1, n)).reshape(batch, steps + 1)
    t = np.arange(steps + 1) * plant.dt
    return Trajectory(t=t, x=x, u=u, r=r, y=y, diverged=diverged)
