"""A nonlinear Crazyflie 2.1 altitude stand-in for the paper's hardware test (sim-to-real).

Motor lag, thrust limits, quadratic drag, more mass and noisy estimates, at 100 Hz.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from generalist_control.simulation.simulate import DIVERGENCE_BOUND, Controller, Trajectory, rk4

__all__ = ["CrazyflieParams", "fly_many"]


@dataclass(frozen=True)
class CrazyflieParams:
    """Parameters of the nonlinear stand-in (SI units)."""

    mass: float = 0.029  # kg: 27 g airframe plus a marker deck
    g: float = 9.81
    drag_linear: float = 0.01  # N s / m
    drag_quadratic: float = 0.02  # N s^2 / m^2
    motor_tau: float = 0.03  # s: first-order lag from command to thrust
    thrust_min: float = 0.0  # N
    thrust_max: float = 0.58  # N: four motors at full throttle
    noise_altitude: float = 0.002  # m, std of the altitude estimate
    noise_velocity: float = 0.02  # m/s, std of the velocity estimate
    loop_rate: float = 100.0  # Hz
    nominal_mass: float = 0.027  # kg: the mass the controllers were designed for
    substeps: int = 10


def _deriv(s: np.ndarray, t_cmd: np.ndarray, p: CrazyflieParams) -> np.ndarray:
    """Derivative of ``[z, w, T]`` (altitude, vertical velocity, thrust)."""
    w, thrust = s[:, 1], s[:, 2]
    drag = p.drag_linear * w + p.drag_quadratic * w * np.abs(w)
    out = np.empty_like(s)
    out[:, 0] = w
    out[:, 1] = (thrust - p.mass * p.g - drag) / p.mass
    out[:, 2] = (t_cmd - thrust) / p.motor_tau
    return out


def fly_many(
    controllers: Sequence[Controller],
    r: np.ndarray,
    control_dt: float = 0.05,
    params: CrazyflieParams | None = None,
    seed: int = 0,
) -> list[Trajectory]:
    """Fly each controller from hover for references ``r`` (B, N), sampled every ``control_dt``.

    A controller commands the thrust deviation from the *nominal* hover thrust; the vehicle is
    heavier. All fly in one loop on the same noise, each as it would alone. Per controller,
    the trajectory at the loop rate: true ``[z, w]``, delivered thrust deviation, altitude.
    """
    p = params or CrazyflieParams()
    r = np.atleast_2d(np.asarray(r, dtype=float))
    batch, steps = r.shape
    m = len(controllers)
    dt = 1.0 / p.loop_rate
    every = int(round(control_dt / dt))
    if every < 1 or abs(every * dt - control_dt) > 1e-9:
        raise ValueError(
            f"control_dt = {control_dt} s is not a multiple of the loop period {dt} s"
        )
    rng = np.random.default_rng(seed)
    hover = p.nominal_mass * p.g
    s = np.zeros((m * batch, 3))
    s[:, 2] = hover  # motors spinning at the nominal hover thrust
    xs = np.zeros((m * batch, steps + 1, 2))
    u = np.zeros((m * batch, steps))
    diverged = np.zeros(m * batch, dtype=bool)
    for c in controllers:
        c.reset(batch)
    u_cmd = np.zeros(m * batch)
    rows = [slice(i * batch, (i + 1) * batch) for i in range(m)]
    with np.errstate(all="ignore"):
        for k in range(steps):
            if k % every == 0:
                noise = rng.normal(size=(batch, 2)) * [p.noise_altitude, p.noise_velocity]
                for c, sl in zip(controllers, rows, strict=True):
                    u_cmd[sl] = np.asarray(c.step(s[sl, :2] + noise, r[:, k]), dtype=float)
            cmd = np.clip(hover + u_cmd, p.thrust_min, p.thrust_max)
            s = rk4(partial(_deriv, t_cmd=cmd, p=p), s, dt / p.substeps, p.substeps)
            diverged |= ~np.all(np.isfinite(s) & (np.abs(s) < DIVERGENCE_BOUND), axis=1)
            u[:, k] = s[:, 2] - hover
            xs[:, k + 1] = np.where(diverged[:, None], xs[:, k], s[:, :2])
    t = np.arange(steps + 1) * dt
    return [
        Trajectory(t=t, x=xs[sl], u=u[sl], r=r, y=xs[sl, :, 0], diverged=diverged[sl])
        for sl in rows
    ]
