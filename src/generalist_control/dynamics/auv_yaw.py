"""REMUS AUV sway-yaw dynamics at constant surge speed ``u0``, with heading (Prestero 2001).

Computed in SI units; state ``[v (cm/s), r (deg/s), psi (deg)]``, rudder in degrees
(docs/notes/plant-dynamics.md).
"""

from __future__ import annotations

import numpy as np

__all__ = ["f"]

_DEG = np.pi / 180.0
_CM = 0.01


def f(
    x: np.ndarray,
    u: np.ndarray,
    *,
    u0: float,
    m: float,
    Izz: float,
    Yvdot: float,
    Yrdot: float,
    Nvdot: float,
    Nrdot: float,
    Yuv: float,
    Yur: float,
    Nuv: float,
    Nur: float,
    Yuudr: float,
    Nuudr: float,
    Yvv: float,
    Yrr: float,
    Nvv: float,
    Nrr: float,
) -> np.ndarray:
    """``[dv/dt, dr/dt, dpsi/dt]`` (batch, 3) for ``x = [v, r, psi]`` and rudder ``u`` (deg).

    The coefficients (SI, rad) are the plant file's ``dynamics.params``.
    """
    x = np.asarray(x, dtype=float)
    v = x[:, 0] * _CM
    r = x[:, 1] * _DEG
    delta = np.asarray(u, dtype=float) * _DEG
    sway = (
        Yuv * u0 * v
        + (Yur - m) * u0 * r
        + Yvv * v * np.abs(v)
        + Yrr * r * np.abs(r)
        + Yuudr * u0**2 * delta
    )
    yaw = Nuv * u0 * v + Nur * u0 * r + Nvv * v * np.abs(v) + Nrr * r * np.abs(r)
    yaw = yaw + Nuudr * u0**2 * delta
    # Solve M [vdot; rdot] = [sway; yaw] by Cramer's rule (M is a constant 2 x 2 matrix).
    m11, m12, m21, m22 = m - Yvdot, -Yrdot, -Nvdot, Izz - Nrdot
    det = m11 * m22 - m12 * m21
    vdot = (m22 * sway - m12 * yaw) / det
    rdot = (m11 * yaw - m21 * sway) / det
    return np.stack([vdot / _CM, rdot / _DEG, x[:, 1]], axis=1)
