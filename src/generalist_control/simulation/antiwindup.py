"""Conditional integration, shared by the LQI expert and the policy runtime.

While the actuator clips the command, the error integral is frozen whenever integrating
would push the command further into the limit.
"""

from __future__ import annotations

import numpy as np

__all__ = ["conditional_increment"]


def conditional_increment(
    dz: np.ndarray, u_cmd: np.ndarray, u_act: np.ndarray, direction: float | np.ndarray
) -> np.ndarray:
    """The integrator increment ``dz``, zeroed where it would wind up.

    Parameters
    ----------
    dz : ndarray
        The unconstrained increment ``dt (r - y)``.
    u_cmd, u_act : ndarray
        The commanded control and the control the actuator delivers.
    direction : float or ndarray
        Sign (or any positive multiple of it) of ``d u / d z`` per row.
    """
    excess = u_cmd - u_act
    winding = (np.abs(excess) > 1e-12) & (np.sign(direction * dz) == np.sign(excess))
    return np.where(winding, 0.0, dz)
