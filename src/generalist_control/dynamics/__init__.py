"""Nonlinear plant dynamics referenced from ``conf/plants/*.yaml`` (``dynamics.f``).

Each module defines ``f(x, u, **params) -> xdot`` in absolute coordinates, batched: ``x``
(batch, n), ``u`` (batch,); the keyword parameters are the plant file's ``dynamics.params``.
"""

from generalist_control.dynamics import auv_yaw, two_tank

__all__ = ["auv_yaw", "two_tank"]
