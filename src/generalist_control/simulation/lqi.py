"""LQI expert design (``dz/dt = r - C x``, ``u = -K [x; z]``) and its sampled controller.

python-control's ``lqr(..., integral_action=C)`` integrates ``+C x``: its ``Ki`` has the
other sign.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_continuous_are

from generalist_control.plants.definition import Plant, PlantConfigError
from generalist_control.simulation.perturbation import Perturbation
from generalist_control.simulation.simulate import discretise

__all__ = [
    "AntiWindupLQIController",
    "LQIController",
    "LQIGains",
    "augment",
    "conditional_increment",
    "design_lqi",
    "sampled_closed_loop",
]


#: Designs per (immutable) plant object.
_DESIGNS: weakref.WeakKeyDictionary[Plant, LQIGains] = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class LQIGains:
    """State gain ``Kx`` (n,), integral gain ``Ki`` and the Riccati solution ``P``."""

    Kx: np.ndarray
    Ki: float
    P: np.ndarray
    poles: np.ndarray

    @property
    def K(self) -> np.ndarray:
        """The full gain row ``[Kx, Ki]`` on the augmented state ``[x; z]``."""
        return np.append(self.Kx, self.Ki)[None, :]


def augment(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The augmented pair ``(A_a, B_a)`` for the state ``[x; z]`` with ``dz/dt = -C x``."""
    n = A.shape[0]
    Aa = np.block([[A, np.zeros((n, 1))], [-C, np.zeros((1, 1))]])
    Ba = np.vstack([B, np.zeros((1, 1))])
    return Aa, Ba


def _equilibrate(M: np.ndarray, iterations: int = 30) -> np.ndarray:
    """``D_r M D_c`` with rows and columns scaled to unit max-norm (Ruiz's iteration)."""
    M = np.array(M, dtype=complex if np.iscomplexobj(M) else float)
    for _ in range(iterations):
        r = np.sqrt(np.abs(M).max(axis=1))
        c = np.sqrt(np.abs(M).max(axis=0))
        M = M / np.where(r > 0, r, 1.0)[:, None] / np.where(c > 0, c, 1.0)[None, :]
    return M


def conditional_increment(
    dz: np.ndarray, u_cmd: np.ndarray, u_act: np.ndarray, direction: float | np.ndarray
) -> np.ndarray:
    """The integrator increment ``dz``, zeroed where it would wind up the clipped actuator.

    ``u_cmd`` is the commanded control, ``u_act`` the delivered one, ``direction`` the sign
    (or any positive multiple of it) of ``du/dz`` per row.
    """
    excess = u_cmd - u_act
    winding = (np.abs(excess) > 1e-12) & (np.sign(direction * dz) == np.sign(excess))
    return np.where(winding, 0.0, dz)


def _check_fit(plant: Plant, Aa: np.ndarray, Ba: np.ndarray) -> None:
    """Refuse a plant with a zero at s = 0 or a non-stabilisable augmented pair."""
    n = plant.order
    system = np.block([[plant.A, plant.B], [plant.C, np.zeros((1, 1))]])
    # A zero at s = 0 makes the Rosenbrock matrix singular. Units rescale its rows and
    # columns, so equilibrate them first: the rank test is then unit-independent.
    sv = np.linalg.svd(_equilibrate(system), compute_uv=False)
    if sv[-1] < 1e-10 * sv[0]:
        raise PlantConfigError(
            f"plant '{plant.name}' is unfit for LQI: it has a transmission zero at s = 0, so "
            "integral action cannot make the output track a constant reference"
        )
    for lam in np.linalg.eigvals(Aa):
        if lam.real >= -1e-9:
            pbh = _equilibrate(np.hstack([lam * np.eye(n + 1) - Aa, Ba]))
            sv = np.linalg.svd(pbh, compute_uv=False)
            if sv[-1] < 1e-9 * sv[0]:
                raise PlantConfigError(
                    f"plant '{plant.name}' is unfit for LQI: the augmented pair (A_a, B_a) is "
                    f"not stabilisable (uncontrollable mode at s = {lam:.4g})"
                )


def sampled_closed_loop(plant: Plant, gains: LQIGains) -> np.ndarray:
    """The closed-loop matrix of the sampled LQI loop (plant ZOH, Euler integrator), r = 0."""
    Ad, Bd = discretise(plant.A, plant.B, plant.dt)
    top = np.hstack([Ad - Bd @ gains.Kx[None, :], -Bd * gains.Ki])
    bottom = np.hstack([-plant.dt * plant.C, np.ones((1, 1))])
    return np.vstack([top, bottom])


def design_lqi(plant: Plant) -> LQIGains:
    """Continuous LQI design for ``plant`` (its linearisation for nonlinear plants).

    Raises
    ------
    PlantConfigError
        If the plant is unfit for LQI: a zero at s = 0, a non-stabilisable augmented pair,
        or a closed loop (continuous or sampled at ``plant.dt``) that is not stable.
    """
    cached = _DESIGNS.get(plant)
    if cached is not None:
        return cached
    Aa, Ba = augment(plant.A, plant.B, plant.C)
    _check_fit(plant, Aa, Ba)
    # python-control's lqr, bit for bit (without its import)
    P = solve_continuous_are(Aa, Ba, plant.Q, plant.R)
    K = np.linalg.solve(plant.R, Ba.T @ P)
    poles, _ = np.linalg.eig(Aa - Ba @ K)
    gains = LQIGains(Kx=K[0, :-1].copy(), Ki=float(K[0, -1]), P=P, poles=poles)
    if np.any(np.real(poles) >= 0):
        raise PlantConfigError(f"plant '{plant.name}': LQI closed loop is not stable")
    rho = np.abs(np.linalg.eigvals(sampled_closed_loop(plant, gains))).max()
    if rho >= 1.0:
        raise PlantConfigError(
            f"plant '{plant.name}': the LQI loop sampled at dt = {plant.dt} s is unstable "
            f"(spectral radius {rho:.4f}); lower the gains (raise lqi.R) or reduce dt"
        )
    _DESIGNS[plant] = gains
    return gains


class LQIController:
    """The LQI law ``u = -Kx x - Ki z`` with a forward-Euler error integrator, batched."""

    def __init__(self, plant: Plant, gains: LQIGains | None = None) -> None:
        self.plant = plant
        self.gains = gains if gains is not None else design_lqi(plant)
        self.z = np.zeros(1)

    def reset(self, batch_size: int) -> None:
        """Zero the integrator for ``batch_size`` parallel runs."""
        self.z = np.zeros(batch_size)

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Control for the current sample, then advance the integrator."""
        u = -(x @ self.gains.Kx) - self.gains.Ki * self.z
        self.z = self.z + self.plant.dt * (r - self.plant.output(x))
        return u


class AntiWindupLQIController(LQIController):
    """LQI with conditional integration (:func:`conditional_increment`) against ``limits``."""

    def __init__(self, plant: Plant, limits: Perturbation, gains: LQIGains | None = None) -> None:
        super().__init__(plant, gains)
        self.limits = limits
        self.u_prev = np.zeros(1)

    def reset(self, batch_size: int) -> None:
        """Zero the integrator and the remembered actuator output."""
        super().reset(batch_size)
        self.u_prev = np.zeros(batch_size)

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Control for the current sample; integrate only where it does not wind up."""
        u_cmd = -(x @ self.gains.Kx) - self.gains.Ki * self.z
        u_act = self.limits.actuate(u_cmd, self.u_prev, self.plant.dt)
        dz = self.plant.dt * (r - self.plant.output(x))
        self.z = self.z + conditional_increment(dz, u_cmd, u_act, -self.gains.Ki)
        self.u_prev = u_act
        return u_cmd
