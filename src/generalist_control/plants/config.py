"""Building a :class:`~generalist_control.plants.plant.Plant` from its configuration.

Every field of ``conf/plants/<name>.yaml`` is checked here (see ``conf/plants/README.md``
for the schema); fitness for LQI (stabilisability, no zero at s = 0) is checked by
:func:`generalist_control.simulation.lqi.design_lqi`.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from generalist_control.plants.plant import (
    MAX_ORDER,
    Dynamics,
    Plant,
    PlantConfigError,
    Signal,
    linearise,
)
from generalist_control.plants.variants import register_spec

__all__ = ["plant_from_config"]


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


def _nonlinear_model(name: str, cfg: Mapping[str, Any], n: int) -> dict[str, Any]:
    """``f``, ``h``, parameters, operating point and the linearisation of a nonlinear plant."""
    dyn = cfg["dynamics"]
    f = _import(str(dyn.get("f", "")), name, "dynamics.f")
    params = {str(k): float(v) for k, v in (dyn.get("params") or {}).items()}
    x_op = _matrix(dyn, "x_op", name, (1, n))[0]
    u_op = float(dyn.get("u_op", 0.0))
    h = _import(str(dyn["h"]), name, "dynamics.h") if dyn.get("h") is not None else None
    f0 = f(x_op[None, :], np.array([u_op]), **params)[0]
    A, B, C_lin = linearise(f, h, x_op, u_op, params)
    # relative to the size of the terms that cancel at the equilibrium (unit-free)
    scale = np.abs(A) @ np.abs(x_op) + np.abs(B[:, 0]) * abs(u_op)
    if np.any(np.abs(f0) > 1e-6 * scale + 1e-12):
        raise PlantConfigError(
            f"plant '{name}': 'dynamics.x_op', 'dynamics.u_op' is not an equilibrium "
            f"(f = {np.array2string(f0, precision=3)})"
        )
    C = C_lin if C_lin is not None else _matrix(cfg, "C", name, (1, n))
    y_op = float(h(x_op[None, :], **params)[0]) if h is not None else float(C[0] @ x_op)
    return {
        "A": A, "B": B, "C": C, "f": f, "h": h, "params": params,
        "x_op": x_op, "u_op": u_op, "y_op": y_op,
    }  # fmt: skip


def _model(name: str, cfg: Mapping[str, Any], n: int) -> dict[str, Any]:
    """The plant's model fields: matrices (linear) or dynamics and linearisation."""
    if cfg.get("dynamics") is not None:
        return _nonlinear_model(name, cfg, n)
    return {
        "A": _matrix(cfg, "A", name, (n, n)),
        "B": _matrix(cfg, "B", name, (n, 1)),
        "C": _matrix(cfg, "C", name, (1, n)),
        "x_op": np.zeros(n),
    }


def _lqi_weights(name: str, lqi: Mapping[str, Any], n: int) -> tuple[np.ndarray, np.ndarray]:
    """``Q`` (n + 1 square, positive semidefinite) and ``R`` (1 x 1, positive)."""
    if "Q" not in lqi or "R" not in lqi:
        raise PlantConfigError(f"plant '{name}': field 'lqi' needs 'Q' and 'R'")
    Q = _weight(lqi["Q"], n + 1, "lqi.Q", name)
    R = _weight(lqi["R"], 1, "lqi.R", name)
    if np.linalg.eigvalsh(Q).min() < -1e-12:
        raise PlantConfigError(f"plant '{name}': field 'lqi.Q' is not positive semidefinite")
    if R[0, 0] <= 0:
        raise PlantConfigError(f"plant '{name}': field 'lqi.R' must be positive definite")
    return Q, R


def _settings(name: str, cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Sample time, amplitude scale and RK4 sub-steps, each checked."""
    dt = float(cfg["dt"])
    if not dt > 0:
        raise PlantConfigError(f"plant '{name}': field 'dt' must be positive, got {dt}")
    scale = float(cfg.get("amplitude_scale", 1.0))
    if not scale > 0:
        raise PlantConfigError(f"plant '{name}': field 'amplitude_scale' must be positive")
    substeps = int(cfg.get("substeps", 10))
    if substeps < 1:
        raise PlantConfigError(f"plant '{name}': field 'substeps' must be at least 1")
    return {"dt": dt, "amplitude_scale": scale, "substeps": substeps}


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
        If a field is missing, has the wrong shape, the weights are not (semi)definite, or
        the ``variants`` block is malformed (:func:`~.variants.register_spec`).
        Fitness for LQI (stabilisability, zero at s = 0) is checked by
        :func:`generalist_control.simulation.lqi.design_lqi`.
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
    settings = _settings(name, cfg)
    model = _model(name, cfg, n)
    Q, R = _lqi_weights(name, cfg["lqi"], n)
    plant = Plant(
        name=name,
        tag=int(cfg["tag"]),
        description=str(cfg["description"]),
        source=str(cfg["source"]),
        states=states,
        input_signal=inp,
        output_signal=out,
        Q=Q,
        R=R,
        **settings,
        **model,
    )
    register_spec(plant, cfg.get("variants"))  # the optional 'variants' block, validated
    return plant
