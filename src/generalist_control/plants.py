"""Plant definitions: a validated, immutable description of one SISO plant.

A plant is either linear, ``dx/dt = A x + B u``, ``y = C x``, or nonlinear,
``dx/dt = f(x, u)``, ``y = h(x)`` with an operating point ``(x_op, u_op)`` at which
``f(x_op, u_op) = 0``. Everything outside this module works in *deviation coordinates*
about the operating point (zero for linear plants): states, outputs, references and
controls in the dataset, the LQI law and the learned policy are all deviations.

Plants are built from configuration (``conf/plants/<name>.yaml``) by
:func:`plant_from_config`, which checks every field before anything is simulated.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "MAX_ORDER",
    "Plant",
    "PlantConfigError",
    "Signal",
    "linearise",
    "plant_from_config",
]

#: Largest plant order the policy handles (states are zero-padded to this length).
MAX_ORDER = 4

Dynamics = Callable[..., np.ndarray]


class PlantConfigError(ValueError):
    """A plant's configuration is invalid; the message names the plant and the field."""


@dataclass(frozen=True)
class Signal:
    """Name and unit of one state, input or output signal."""

    name: str
    unit: str


@dataclass(frozen=True, eq=False)
class Plant:
    """One SISO plant with its LQI weights.

    Attributes
    ----------
    name, tag : str, int
        Catalogue name and the stable integer system tag fed to the policy.
    A, B, C : ndarray
        The model (linear plants) or its linearisation at the operating point.
    Q, R : ndarray
        LQI weights on the augmented state ``[x; z]`` (size ``n + 1``) and on the input.
    f, h : callable or None
        Nonlinear dynamics ``f(x, u, **params)`` and output ``h(x, **params)`` in absolute
        coordinates, batched over the leading axis; ``None`` for linear plants.
    x_op, u_op, y_op : ndarray, float, float
        Operating point; zero for linear plants.
    amplitude_scale : float
        Factor applied to the data stage's step-amplitude grid for this plant.
    """

    name: str
    tag: int
    description: str
    source: str
    states: tuple[Signal, ...]
    input_signal: Signal
    output_signal: Signal
    dt: float
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    f: Dynamics | None = None
    h: Dynamics | None = None
    params: Mapping[str, float] = field(default_factory=dict)
    x_op: np.ndarray | None = None
    u_op: float = 0.0
    y_op: float = 0.0
    substeps: int = 10
    amplitude_scale: float = 1.0

    @property
    def order(self) -> int:
        """Number of states ``n``."""
        return self.A.shape[0]

    @property
    def is_linear(self) -> bool:
        """True when the plant is simulated with its linear model."""
        return self.f is None

    def deriv(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """State derivative in deviation coordinates, batched.

        Parameters
        ----------
        x : ndarray, shape (batch, n)
            State deviation from the operating point.
        u : ndarray, shape (batch,)
            Input deviation.
        """
        if self.f is None:
            return x @ self.A.T + u[:, None] * self.B[:, 0]
        return self.f(x + self.x_op, u + self.u_op, **self.params)

    def output(self, x: np.ndarray) -> np.ndarray:
        """Output deviation ``y - y_op`` for a batch of state deviations ``(batch, n)``."""
        if self.h is None:
            return x @ self.C[0]
        return self.h(x + self.x_op, **self.params) - self.y_op


def _import(path: str, plant: str, key: str) -> Dynamics:
    module, _, attr = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError) as exc:
        raise PlantConfigError(
            f"plant '{plant}': field '{key}' = '{path}' does not name an importable "
            "function (write it as 'package.module.function')"
        ) from exc


def _matrix(cfg: Mapping[str, Any], key: str, plant: str, shape: tuple[int, int]) -> np.ndarray:
    try:
        m = np.atleast_2d(np.asarray(cfg[key], dtype=float))
    except KeyError:
        raise PlantConfigError(f"plant '{plant}': missing field '{key}'") from None
    except (TypeError, ValueError) as exc:
        raise PlantConfigError(f"plant '{plant}': field '{key}' is not numeric") from exc
    if m.shape != shape:
        raise PlantConfigError(
            f"plant '{plant}': field '{key}' has shape {m.shape}, expected {shape}"
        )
    if not np.all(np.isfinite(m)):
        raise PlantConfigError(f"plant '{plant}': field '{key}' contains NaN or inf")
    return m


def _weight(value: Any, n: int, key: str, plant: str) -> np.ndarray:
    """A weight given as a scalar, a diagonal (list of n) or a full n x n matrix."""
    try:
        w = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise PlantConfigError(f"plant '{plant}': field '{key}' is not numeric") from exc
    if w.ndim == 0 and n == 1:
        w = w.reshape(1, 1)
    elif w.ndim == 1 and w.shape[0] == n:
        w = np.diag(w)
    if w.shape != (n, n):
        raise PlantConfigError(
            f"plant '{plant}': field '{key}' has shape {np.shape(value)}; expected a list of "
            f"{n} diagonal entries or a {n}x{n} matrix"
        )
    if not np.all(np.isfinite(w)):
        raise PlantConfigError(f"plant '{plant}': field '{key}' contains NaN or inf")
    if not np.allclose(w, w.T):
        raise PlantConfigError(f"plant '{plant}': field '{key}' is not symmetric")
    return w


def linearise(
    f: Dynamics, h: Dynamics | None, x_op: np.ndarray, u_op: float, params: Mapping[str, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Jacobians of ``f`` (and ``h``) at the operating point by central differences.

    Returns
    -------
    A, B, C : ndarray
        ``df/dx`` (n x n), ``df/du`` (n x 1) and ``dh/dx`` (1 x n, ``None`` without ``h``).
    """
    n = x_op.shape[0]
    eps = 1e-6 * np.maximum(1.0, np.abs(np.append(x_op, u_op)))
    xs = np.tile(x_op, (2 * n + 2, 1))
    us = np.full(2 * n + 2, float(u_op))
    for i in range(n):
        xs[2 * i, i] += eps[i]
        xs[2 * i + 1, i] -= eps[i]
    us[2 * n] += eps[n]
    us[2 * n + 1] -= eps[n]
    fx = f(xs, us, **params)
    d = (fx[0::2] - fx[1::2]) / (2 * eps[:, None])
    A, B = d[:n].T, d[n:].T
    C = None
    if h is not None:
        hx = h(xs[: 2 * n], **params)
        C = ((hx[0::2] - hx[1::2]) / (2 * eps[:n]))[None, :]
    return A, B, C


def _signals(cfg: Mapping[str, Any], key: str, plant: str) -> tuple[Signal, ...]:
    items = cfg.get(key)
    if items is None:
        raise PlantConfigError(f"plant '{plant}': missing field '{key}'")
    if isinstance(items, Mapping):
        items = [items]
    try:
        return tuple(Signal(str(s["name"]), str(s["unit"])) for s in items)
    except (KeyError, TypeError) as exc:
        raise PlantConfigError(
            f"plant '{plant}': each entry of '{key}' needs 'name' and 'unit'"
        ) from exc


def plant_from_config(name: str, cfg: Mapping[str, Any]) -> Plant:
    """Build and validate a :class:`Plant` from its configuration mapping.

    Parameters
    ----------
    name : str
        Catalogue name (the file stem of ``conf/plants/<name>.yaml``).
    cfg : mapping
        The plant's configuration (see ``conf/plants/README.md`` for the schema).

    Raises
    ------
    PlantConfigError
        If a field is missing, has the wrong shape, or the weights are not (semi)definite.
        Fitness for LQI (stabilisability, zero at s = 0) is checked by
        :func:`generalist_control.lqi.design_lqi`.
    """
    for key in ("tag", "description", "source", "dt", "lqi"):
        if key not in cfg:
            raise PlantConfigError(f"plant '{name}': missing field '{key}'")
    states = _signals(cfg, "states", name)
    (inp,) = _signals(cfg, "input", name)
    (out,) = _signals(cfg, "output", name)
    n = len(states)
    if not 1 <= n <= MAX_ORDER:
        raise PlantConfigError(
            f"plant '{name}': {n} states listed in 'states'; orders 1..{MAX_ORDER} are supported"
        )
    dt = float(cfg["dt"])
    if not dt > 0:
        raise PlantConfigError(f"plant '{name}': field 'dt' must be positive, got {dt}")

    f = h = None
    params: dict[str, float] = {}
    x_op = np.zeros(n)
    u_op = y_op = 0.0
    dyn = cfg.get("dynamics")
    if dyn is None:
        A = _matrix(cfg, "A", name, (n, n))
        B = _matrix(cfg, "B", name, (n, 1))
        C = _matrix(cfg, "C", name, (1, n))
    else:
        f = _import(str(dyn.get("f", "")), name, "dynamics.f")
        params = {str(k): float(v) for k, v in (dyn.get("params") or {}).items()}
        x_op = _matrix(dyn, "x_op", name, (1, n))[0]
        u_op = float(dyn.get("u_op", 0.0))
        if dyn.get("h") is not None:
            h = _import(str(dyn["h"]), name, "dynamics.h")
        f0 = f(x_op[None, :], np.array([u_op]), **params)[0]
        A, B, C_lin = linearise(f, h, x_op, u_op, params)
        # relative to the size of the terms that cancel at the equilibrium (unit-free)
        scale = np.abs(A) @ np.abs(x_op) + np.abs(B[:, 0]) * abs(u_op)
        if np.any(np.abs(f0) > 1e-6 * scale + 1e-12):
            raise PlantConfigError(
                f"plant '{name}': 'dynamics.x_op', 'dynamics.u_op' is not an equilibrium "
                f"(f = {np.array2string(f0, precision=3)})"
            )
        C = C_lin if h is not None else _matrix(cfg, "C", name, (1, n))
        y_op = float(h(x_op[None, :], **params)[0]) if h is not None else float(C[0] @ x_op)

    lqi = cfg["lqi"]
    if "Q" not in lqi or "R" not in lqi:
        raise PlantConfigError(f"plant '{name}': field 'lqi' needs 'Q' and 'R'")
    Q = _weight(lqi["Q"], n + 1, "lqi.Q", name)
    R = _weight(lqi["R"], 1, "lqi.R", name)
    if np.linalg.eigvalsh(Q).min() < -1e-12:
        raise PlantConfigError(f"plant '{name}': field 'lqi.Q' is not positive semidefinite")
    if R[0, 0] <= 0:
        raise PlantConfigError(f"plant '{name}': field 'lqi.R' must be positive definite")

    scale = float(cfg.get("amplitude_scale", 1.0))
    if not scale > 0:
        raise PlantConfigError(f"plant '{name}': field 'amplitude_scale' must be positive")
    substeps = int(cfg.get("substeps", 10))
    if substeps < 1:
        raise PlantConfigError(f"plant '{name}': field 'substeps' must be at least 1")
    return Plant(
        name=name,
        tag=int(cfg["tag"]),
        description=str(cfg["description"]),
        source=str(cfg["source"]),
        states=states,
        input_signal=inp,
        output_signal=out,
        dt=dt,
        A=A,
        B=B,
        C=C,
        Q=Q,
        R=R,
        f=f,
        h=h,
        params=params,
        x_op=x_op,
        u_op=u_op,
        y_op=y_op,
        substeps=substeps,
        amplitude_scale=scale,
    )
