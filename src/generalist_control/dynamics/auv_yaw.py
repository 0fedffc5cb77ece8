r"""REMUS AUV horizontal-plane (sway-yaw) dynamics at constant surge speed, with heading.

The model is the sway and yaw equations of Prestero's six-degree-of-freedom REMUS model
(T. Prestero, *Verification of a six-degree of freedom simulation model for the REMUS
autonomous underwater vehicle*, MSc thesis, MIT/WHOI, 2001), with the surge speed held at
``u0`` and roll/pitch/heave motion neglected:

.. math::
    M \begin{bmatrix} \dot v \\ \dot r \end{bmatrix} =
    \begin{bmatrix}
      Y_{uv} u_0 v + (Y_{ur} - m) u_0 r + Y_{v|v|} v|v| + Y_{r|r|} r|r|
        + Y_{uu\delta_r} u_0^2 \delta \\
      N_{uv} u_0 v + N_{ur} u_0 r + N_{v|v|} v|v| + N_{r|r|} r|r|
        + N_{uu\delta_r} u_0^2 \delta
    \end{bmatrix},
    \qquad \dot\psi = r,

with ``M = [[m - Y_vdot, -Y_rdot], [-N_vdot, Izz - N_rdot]]`` (centre of gravity on the
centre of buoyancy axis, ``x_g = 0``). The hydrodynamic equations use SI units and radians;
the state and input exposed to the rest of the package use degrees so that the data stage's
step grid of +-20 means heading steps of +-20 degrees:

- ``x[:, 0]``: sway velocity ``v`` in cm/s (sway stays at a few cm/s in manoeuvres, so
  centimetres keep it on the same scale as the yaw rate in deg/s);
- ``x[:, 1]``: yaw rate ``r`` in deg/s;
- ``x[:, 2]``: heading ``psi`` in deg;
- ``u``: rudder angle ``delta`` in deg.

At ``u0 = 1.54`` m/s the linearisation about straight-line motion has poles at 0, -2.33 and
+1.02 rad/s: with these coefficients the vehicle is directionally unstable in open loop
(``N_uv``, which lumps body lift, fin lift and the Munk moment, is destabilising).
"""

from __future__ import annotations

import numpy as np

__all__ = ["PRESTERO_2001", "f"]

_DEG = np.pi / 180.0
_CM = 0.01

#: Prestero (2001) REMUS coefficients (SI units, rad), with the nominal surge speed ``u0``.
PRESTERO_2001: dict[str, float] = {
    "u0": 1.54,
    "m": 30.48,
    "Izz": 3.45,
    "Yvdot": -35.5,
    "Yrdot": 1.93,
    "Nvdot": 1.93,
    "Nrdot": -4.88,
    "Yuv": -28.6,
    "Yur": 5.22,
    "Nuv": -24.0,
    "Nur": -2.0,
    "Yuudr": 9.64,
    "Nuudr": -6.15,
    "Yvv": -1310.0,
    "Yrr": 0.632,
    "Nvv": -3.18,
    "Nrr": -94.0,
}


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
    """State derivative of the REMUS sway-yaw-heading model, batched.

    ``x`` (batch, 3) is ``[v (cm/s), r (deg/s), psi (deg)]``, ``u`` (batch,) the rudder
    angle in degrees; returns ``[dv/dt (cm/s^2), dr/dt (deg/s^2), dpsi/dt (deg/s)]``. The
    keyword coefficients are those of :data:`PRESTERO_2001` (see the module docstring):
    surge speed ``u0`` (m/s), mass ``m`` and inertia ``Izz``, added mass ``Yvdot .. Nrdot``,
    lift and cross terms ``Yuv .. Nur``, rudder ``Yuudr, Nuudr``, cross-flow drag
    ``Yvv .. Nrr``.

    Examples
    --------
    >>> f(np.zeros((1, 3)), np.zeros(1), **PRESTERO_2001).tolist()
    [[0.0, 0.0, 0.0]]
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
