"""Nonlinear plant dynamics ``f(x, u, **params)``, batched, named by ``conf/plants/*.yaml``."""

from generalist_control.dynamics import auv_yaw, two_tank

__all__ = ["auv_yaw", "two_tank"]
