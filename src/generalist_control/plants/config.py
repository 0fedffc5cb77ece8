"""A :class:`~generalist_control.plants.definition.Plant` from its file: every field checked once.

Also a plant given at run time (the model card route): a plant YAML anywhere, or a model dict,
where ``tag``, ``description`` and ``source`` may be left out. Fitness for LQI is checked by
:func:`generalist_control.simulation.lqi.design_lqi`.
"""

from __future__ import annotations

import importlib
import numbers
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from generalist_control.plants.definition import (
    MAX_ORDER,
    Dynamics,
    Plant,
    PlantConfigError,
    Signal,
    linearise,
)
from generalist_control.plants.variants import register_spec

__all__ = [
    "MAX_ENTRY",
    "MODEL_KEYS",
    "plant_from_config",
    "plant_from_file",
    "plant_from_model",
    "read_plant_file",
]

#: The largest magnitude of a number in a plant file (the Riccati solver overflows beyond).
MAX_ENTRY = 1e12

#: The keys of a model dict (``name`` optional).
MODEL_KEYS = ("A", "B", "C", "dt", "Q", "R")

#: What a plant given at run time need not say: it gets a row of its own; its tag is unused.
_DEFAULTS = {"tag": 0, "description": "a plant given at run time", "source": "given"}

#: A plant's name, the key Hydra reaches it by: no dots.
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _import(path: str, plant: str, key: str) -> Dynamics:
    module, _, attr = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError) as exc:
        raise PlantConfigError(
            f"plant '{plant}': field '{key}' = '{path}' does not name an importable "
            "function (write it as 'package.module.function')"
        ) from exc


def _matrix(spec: Mapping[str, Any], key: str, plant: str, shape: tuple[int, int]) -> np.ndarray:
    try:
        m = np.atleast_2d(np.asarray(spec[key], dtype=float))
    except KeyError:
        raise PlantConfigError(f"plant '{plant}': missing field '{key}'") from None
    except (TypeError, ValueError) as exc:
        raise PlantConfigError(f"plant '{plant}': field '{key}' is not numeric") from exc
    if m.shape != shape:
        raise PlantConfigError(
            f"plant '{plant}': field '{key}' has shape {m.shape}, expected {shape}"
        )
    return _sane(m, key, plant)


def _sane(m: np.ndarray, key: str, plant: str) -> np.ndarray:
    """``m`` if every entry is finite and within +-:data:`MAX_ENTRY`."""
    if not np.all(np.isfinite(m)):
        raise PlantConfigError(f"plant '{plant}': field '{key}' contains NaN or inf")
    if np.abs(m).max(initial=0.0) > MAX_ENTRY:
        raise PlantConfigError(
            f"plant '{plant}': field '{key}' has an entry of {np.abs(m).max():.3g}, beyond "
            f"+-{MAX_ENTRY:.0e}; rescale the plant's units (states, input, output) so that "
            "its numbers are of moderate size (conf/plants/README.md, units)"
        )
    return m


def _number(spec: Mapping[str, Any], key: str, plant: str, default: float | None = None) -> float:
    """The field ``key``: a finite real number (``default`` when absent, if given)."""
    value = spec.get(key, default) if default is not None else spec[key]
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise PlantConfigError(f"plant '{plant}': field '{key}' must be a number, got {value!r}")
    return float(_sane(np.array([value], dtype=float), key, plant)[0])


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
    _sane(w, key, plant)
    if not np.allclose(w, w.T):
        raise PlantConfigError(f"plant '{plant}': field '{key}' is not symmetric")
    return w


def _signals(spec: Mapping[str, Any], key: str, plant: str) -> tuple[Signal, ...]:
    items = spec.get(key)
    if items is None:
        what = "one {name, unit} per state" if key == "states" else "{name, unit}"
        raise PlantConfigError(f"plant '{plant}': missing field '{key}' ({what})")
    if isinstance(items, Mapping):
        items = [items]
    try:
        return tuple(Signal(str(s["name"]), str(s["unit"])) for s in items)
    except (KeyError, TypeError) as exc:
        raise PlantConfigError(
            f"plant '{plant}': each entry of '{key}' needs 'name' and 'unit'"
        ) from exc


def _nonlinear_model(name: str, spec: Mapping[str, Any], n: int) -> dict[str, Any]:
    """``f``, ``h``, parameters, operating point and the linearisation of a nonlinear plant."""
    dyn = spec["dynamics"]
    f = _import(str(dyn.get("f", "")), name, "dynamics.f")
    params = dyn.get("params") or {}
    params = {str(k): _number(params, k, name) for k in params}
    x_op = _matrix(dyn, "x_op", name, (1, n))[0]
    u_op = _number(dyn, "u_op", name, 0.0)
    h = _import(str(dyn["h"]), name, "dynamics.h") if dyn.get("h") is not None else None
    f0 = f(x_op[None, :], np.array([u_op]), **params)[0]
    A, B, C_lin = linearise(f, h, x_op, u_op, params)
    scale = np.abs(A) @ np.abs(x_op) + np.abs(B[:, 0]) * abs(u_op)
    if np.any(np.abs(f0) > 1e-6 * scale + 1e-12):
        raise PlantConfigError(
            f"plant '{name}': 'dynamics.x_op', 'dynamics.u_op' is not an equilibrium "
            f"(f = {np.array2string(f0, precision=3)})"
        )
    C = C_lin if C_lin is not None else _matrix(spec, "C", name, (1, n))
    y_op = float(h(x_op[None, :], **params)[0]) if h is not None else float(C[0] @ x_op)
    return {
        "A": A, "B": B, "C": C, "f": f, "h": h, "params": params,
        "x_op": x_op, "u_op": u_op, "y_op": y_op,
    }  # fmt: skip


def _model(name: str, spec: Mapping[str, Any], n: int) -> dict[str, Any]:
    """The plant's model fields: matrices (linear) or dynamics and linearisation."""
    if spec.get("dynamics") is not None:
        return _nonlinear_model(name, spec, n)
    return {
        "A": _matrix(spec, "A", name, (n, n)),
        "B": _matrix(spec, "B", name, (n, 1)),
        "C": _matrix(spec, "C", name, (1, n)),
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


def _settings(name: str, spec: Mapping[str, Any]) -> dict[str, Any]:
    """Sample time, amplitude scale and RK4 sub-steps, each checked."""
    dt = _number(spec, "dt", name)
    if not dt > 0:
        raise PlantConfigError(f"plant '{name}': field 'dt' must be positive, got {dt}")
    scale = _number(spec, "amplitude_scale", name, 1.0)
    if not scale > 0:
        raise PlantConfigError(f"plant '{name}': field 'amplitude_scale' must be positive")
    substeps = spec.get("substeps", 10)
    if isinstance(substeps, bool) or not isinstance(substeps, numbers.Integral) or substeps < 1:
        raise PlantConfigError(
            f"plant '{name}': field 'substeps' must be an integer >= 1, got {substeps!r}"
        )
    return {"dt": dt, "amplitude_scale": scale, "substeps": int(substeps)}


def _identity(name: str, spec: Any) -> int:
    """The file is a mapping, the name a Hydra key, the tag a non-negative integer."""
    if not isinstance(spec, Mapping):
        raise PlantConfigError(
            f"plant '{name}': the file holds a {type(spec).__name__}, not the mapping of a "
            "plant's fields (tag, dt, states, ...; conf/plants/README.md)"
        )
    if not _NAME.fullmatch(name):
        plain = re.sub(r"\W", "_", name)
        raise PlantConfigError(
            f"plant '{name}': a plant's name (its file's stem) must be letters, digits and "
            f"underscores (Hydra splits keys at dots); rename the file, e.g. {plain}.yaml"
        )
    for key in ("tag", "description", "source", "dt", "lqi"):
        if key not in spec:
            raise PlantConfigError(f"plant '{name}': missing field '{key}'")
    tag = spec["tag"]
    if isinstance(tag, bool) or not isinstance(tag, numbers.Integral) or tag < 0:
        raise PlantConfigError(
            f"plant '{name}': field 'tag' must be a non-negative integer (the policy's row "
            f"for the plant), got {tag!r}"
        )
    return int(tag)


def plant_from_config(name: str, spec: Any, source: str | Path | None = None) -> Plant:
    """Build and validate a :class:`Plant` named ``name`` from its spec (a plant file's mapping).

    ``spec`` follows ``conf/plants/README.md``; ``source``, the file it was read from, is
    named first in every refusal.

    Raises
    ------
    PlantConfigError
        Naming the field: not a mapping, a bad name or tag, a field missing, of the wrong
        shape, not finite or beyond +-:data:`MAX_ENTRY`, weights not (semi)definite, or a
        malformed ``variants`` block.
    """
    try:
        return _plant(name, spec)
    except PlantConfigError as exc:
        if source is None:
            raise
        raise PlantConfigError(f"{source}: {exc}") from None


def _plant(name: str, spec: Any) -> Plant:
    tag = _identity(name, spec)
    states = _signals(spec, "states", name)
    (inp,) = _signals(spec, "input", name)
    (out,) = _signals(spec, "output", name)
    n = len(states)
    if not 1 <= n <= MAX_ORDER:
        raise PlantConfigError(
            f"plant '{name}': {n} states listed in 'states'; orders 1..{MAX_ORDER} are supported"
        )
    settings = _settings(name, spec)
    model = _model(name, spec, n)
    Q, R = _lqi_weights(name, spec["lqi"], n)
    plant = Plant(
        name=name,
        tag=tag,
        description=str(spec["description"]),
        source=str(spec["source"]),
        states=states,
        input_signal=inp,
        output_signal=out,
        Q=Q,
        R=R,
        **settings,
        **model,
    )
    register_spec(plant, spec.get("variants"))
    return plant


def plant_from_model(model: Mapping[str, Any], name: str | None = None) -> Plant:
    """A :class:`Plant` from a model dict (keys :data:`MODEL_KEYS`, ``name`` optional).

    E.g. ``{"A": [[0, 1], [-2, -3]], "B": [[0], [1]], "C": [[1, 0]], "dt": 0.05,
    "Q": [1, 1, 10], "R": 1.0}``.

    Raises
    ------
    PlantConfigError
        A missing or unknown key, a matrix of the wrong shape, NaN or inf, weights that are
        not (semi)definite; the message names the key.
    """
    label = str(name or model.get("name") or "given")
    where = f"model dict '{label}'"
    missing = [k for k in MODEL_KEYS if k not in model]
    unknown = sorted(set(model) - {*MODEL_KEYS, "name"})
    if missing or unknown:
        raise PlantConfigError(
            f"{where}: needs the keys {list(MODEL_KEYS)} (and optionally 'name'); "
            + (f"missing {missing}" if missing else f"unknown {unknown}")
        )
    try:
        n = len(model["A"])
    except TypeError:
        raise PlantConfigError(
            f"{where}: field 'A' must be a square matrix (a list of rows)"
        ) from None
    spec = {
        **_DEFAULTS, **_signal_names(n), "dt": model["dt"],
        **{k: model[k] for k in ("A", "B", "C")}, "lqi": {"Q": model["Q"], "R": model["R"]},
    }  # fmt: skip
    return plant_from_config(label, spec)


def _signal_names(n: int) -> dict[str, Any]:
    """Signal names for a plant given without them: states ``x1 ..``, input ``u``, output ``y``."""
    return {
        "states": [{"name": f"x{i + 1}", "unit": "-"} for i in range(n)],
        "input": {"name": "u", "unit": "-"},
        "output": {"name": "y", "unit": "-"},
    }


def read_plant_file(path: Path) -> Any:
    """The plain contents of a plant YAML, interpolations resolved.

    Raises
    ------
    PlantConfigError
        If the file is not YAML, naming it.
    """
    try:
        return OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except (yaml.YAMLError, OmegaConfBaseException) as exc:
        raise PlantConfigError(f"{path}: not a YAML file ({exc})") from None


def plant_from_file(path: str | Path) -> Plant:
    """A :class:`Plant` from a plant YAML file given at run time (its name: the file's stem).

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    PlantConfigError
        If the file is not a plant (not YAML, not a mapping, a field missing or malformed).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no plant file at {path}")
    spec = read_plant_file(path)
    if not isinstance(spec, dict) or not ({"A", "dynamics"} & set(spec)):
        raise PlantConfigError(
            f"{path} is not a plant file: a plant YAML is a mapping with the model (A, B, C "
            "or dynamics), dt and lqi; states, input, output name its signals (conf/plants/"
            "README.md)"
        )
    names = _signal_names(len(spec["A"])) if isinstance(spec.get("A"), list) else {}
    return plant_from_config(path.stem, {**_DEFAULTS, **names, **spec})
