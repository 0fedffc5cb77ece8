"""Nonlinear plant dynamics referenced from ``conf/plants/*.yaml`` (``dynamics.f``).

Each module defines ``f(x, u, **params) -> xdot`` in absolute coordinates, vectorised over
a leading batch axis: ``x`` has shape ``(batch, n)``, ``u`` shape ``(batch,)`` and the result
shape ``(batch, n)``. The keyword parameters are the plant file's ``dynamics.params``.

Modules
-------
auv_yaw
    REMUS AUV sway-yaw-heading dynamics at constant surge speed (Prestero 2001).
two_tank
    Two cascaded tanks with Torricelli outflow.
"""

from generalist_control.dynamics import auv_yaw, two_tank

__all__ = ["auv_yaw", "two_tank"]
