"""Two cascaded tanks with Torricelli outflow ``q = a sqrt(2 g h)`` (nonlinear).

``A1 h1' = q_in - q1``, ``A2 h2' = q1 - q2``; levels in cm, areas in cm^2, flows in cm^3/s.
A level below zero has no outflow. Linearised at ``h_i``: ``T_i = (A_i / a_i) sqrt(2 h_i / g)``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["f"]


def _outflow(a: float, h: np.ndarray, g: float) -> np.ndarray:
    """Torricelli outflow, none below an empty tank."""
    return a * np.sqrt(2.0 * g * np.maximum(h, 0.0))


def f(
    x: np.ndarray,
    u: np.ndarray,
    *,
    A1: float,
    A2: float,
    a1: float,
    a2: float,
    g: float = 981.0,
) -> np.ndarray:
    """``[dh1/dt, dh2/dt]`` (batch, 2) for levels ``x = [h1, h2]`` and pump inflows ``u``.

    Cross-sections ``A1``, ``A2`` and orifice areas ``a1``, ``a2`` in cm^2, ``g`` in cm/s^2.
    """
    x = np.asarray(x, dtype=float)
    q1 = _outflow(a1, x[:, 0], g)
    q2 = _outflow(a2, x[:, 1], g)
    return np.stack([(np.asarray(u, dtype=float) - q1) / A1, (q1 - q2) / A2], axis=1)
