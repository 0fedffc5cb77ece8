"""Randomised reference families and random initial states, for data, DAgger and evaluation.

Draws come from ``default_rng(seed + 1000 * plant.tag)``; a random initial state is one the
plant visits in operation: within its :func:`state_envelope` (``x0_draw: box``, for physical
state coordinates) or a Gaussian with its visited states' second moment (``visited``, the
same in any state coordinates: drawn plants, docs/notes/plant-families.md).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from generalist_control.plants.definition import Plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import (
    PerPlantController,
    Run,
    Segment,
    simulate_stacked,
)

__all__ = [
    "FAMILIES",
    "family_references",
    "family_spec",
    "state_envelope",
    "state_envelopes",
    "visited_moment",
    "visited_root",
]


def _range(spec: Mapping[str, Any], key: str) -> tuple[float, float]:
    value = spec[key]
    if isinstance(value, int | float):
        return float(value), float(value)
    lo, hi = (float(v) for v in value)
    if hi < lo:
        raise ValueError(f"'{key}' must be [low, high] with low <= high, got {list(value)}")
    return lo, hi


def _staircase(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, limit = int(spec["count"]), float(spec["limit"])
    lo, hi = _range(spec, "levels")
    r = np.empty((count, len(t)))
    for b in range(count):
        n = int(rng.integers(int(lo), int(hi) + 1))
        levels = rng.uniform(-limit, limit, size=n)
        r[b] = levels[np.minimum((np.arange(len(t)) * n) // len(t), n - 1)]
    return r


def _sines(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, offset = int(spec["count"]), float(spec["offset"])
    amp = rng.uniform(*_range(spec, "amplitude"), size=(count, 1))
    w_lo, w_hi = _range(spec, "omega")
    omega = np.exp(rng.uniform(np.log(w_lo), np.log(w_hi), size=(count, 1)))
    phase = rng.uniform(0.0, 2 * np.pi, size=(count, 1))
    c = rng.uniform(-offset, offset, size=(count, 1))
    return c + amp * np.sin(omega * t[None, :] + phase)


def _sweep(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, offset = int(spec["count"]), float(spec["offset"])
    amp = rng.uniform(*_range(spec, "amplitude"), size=(count, 1))
    w0, w1 = _range(spec, "omega")
    phase = rng.uniform(0.0, 2 * np.pi, size=(count, 1)) if count > 1 else np.zeros((1, 1))
    c = rng.uniform(-offset, offset, size=(count, 1))
    span = max(float(t[-1]), 1e-12)
    angle = w0 * t + 0.5 * (w1 - w0) * t**2 / span  # instantaneous frequency w0 -> w1
    return c + amp * np.sin(angle[None, :] + phase)


def _ramps(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, offset = int(spec["count"]), float(spec["offset"])
    slope = rng.uniform(*_range(spec, "slope"), size=(count, 1))
    slope *= rng.choice([-1.0, 1.0], size=(count, 1))
    c = rng.uniform(-offset, offset, size=(count, 1))
    return c + slope * t[None, :]


def _hold(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, limit = int(spec["count"]), float(spec["limit"])
    return np.repeat(rng.uniform(-limit, limit, size=(count, 1)), len(t), axis=1)


Family = Callable[[Mapping[str, Any], np.ndarray, np.random.Generator], np.ndarray]

#: ``kind`` -> generator of unscaled references; each reads its parameters from ``spec``.
FAMILIES: dict[str, Family] = {
    "staircase": _staircase,
    "sines": _sines,
    "sweep": _sweep,
    "ramps": _ramps,
    "hold": _hold,
}


#: Each family's parameters and their defaults, the one place they live (and :data:`_COMMON`).
FAMILY_PARAMETERS: dict[str, dict[str, Any]] = {
    "staircase": {"count": 8, "limit": 10.0, "levels": [2, 4]},
    "sines": {"count": 8, "offset": 2.0, "amplitude": [0.2, 3.0], "omega": [0.2, 3.0]},
    "sweep": {"count": 1, "offset": 0.0, "amplitude": 1.0, "omega": [0.1, 2.0]},
    "ramps": {"count": 6, "offset": 2.0, "slope": [0.05, 1.0]},
    "hold": {"count": 8, "limit": 5.0},
}
_COMMON = {"seed": 0, "x0_amplitude": 3.0, "x0_scale": 1.0, "x0_fraction": 0.0, "x0_draw": "box"}
#: How a random initial state is drawn (``x0_draw``).
X0_DRAWS = ("box", "visited")


def family_spec(spec: Mapping[str, Any], extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """``spec`` of a family with its kind's defaults filled in (:data:`FAMILY_PARAMETERS`).

    Raises
    ------
    ValueError
        An unknown ``kind``, or a key the kind does not take (``extra``: keys the caller reads).
    """
    kind = spec.get("kind")
    if kind not in FAMILIES:
        raise ValueError(f"family kind '{kind}' is not one of {', '.join(FAMILIES)}")
    defaults = {**_COMMON, **FAMILY_PARAMETERS[kind]}
    if kind == "hold":
        defaults["x0_fraction"] = 1.0
    unknown = sorted(set(spec) - set(defaults) - {"kind", *extra})
    if unknown:
        raise ValueError(f"{unknown} are not parameters of a '{kind}' family: {sorted(defaults)}")
    out = {**defaults, **spec}
    if out["x0_draw"] not in X0_DRAWS:
        raise ValueError(f"x0_draw must be one of {', '.join(X0_DRAWS)}, got '{out['x0_draw']}'")
    return out


#: Per plant and (amplitude, duration): the visited states' envelope (n,) and second moment.
_VISITED: weakref.WeakKeyDictionary[
    Plant, dict[tuple[float, float], tuple[np.ndarray, np.ndarray]]
] = weakref.WeakKeyDictionary()


def state_envelope(plant: Plant, amplitude: float = 3.0, duration: float = 10.0) -> np.ndarray:
    """Largest ``|x_i|`` (n,) along the LQI expert's responses to scaled steps of +-amplitude."""
    return state_envelopes([(plant, amplitude)], duration)[0]


def visited_moment(plant: Plant, amplitude: float = 3.0, duration: float = 10.0) -> np.ndarray:
    """Second moment ``E[x x']`` (n, n) of the states along :func:`state_envelope`'s responses."""
    state_envelopes([(plant, amplitude)], duration)
    return _VISITED[plant][float(amplitude), float(duration)][1].copy()


def visited_root(plant: Plant, amplitude: float = 3.0) -> np.ndarray:
    """A root ``S`` (n, n) of :func:`visited_moment` (``S S^T``): ``S z`` is a visited state."""
    w, v = np.linalg.eigh(visited_moment(plant, amplitude))
    return v * np.sqrt(np.clip(w, 0.0, None))


def state_envelopes(
    requests: Sequence[tuple[Plant, float]], duration: float = 10.0
) -> list[np.ndarray]:
    """:func:`state_envelope` of many ``(plant, amplitude)``, the missing ones in one loop."""
    missing = list(dict.fromkeys(
        (p, float(a)) for p, a in requests
        if (float(a), float(duration)) not in _VISITED.get(p, {})
    ))  # fmt: skip
    by_dt: dict[float, list[tuple[Plant, float]]] = {}
    for p, a in missing:
        by_dt.setdefault(p.dt, []).append((p, a))
    for todo in by_dt.values():
        runs = []
        for p, a in todo:
            steps, amp = int(round(duration / p.dt)), a * p.amplitude_scale
            runs.append(Run(p, np.array([[amp] * steps, [-amp] * steps])))
        (trajs,) = simulate_stacked([Segment(PerPlantController(LQIController), runs)])
        for (p, a), tr in zip(todo, trajs, strict=True):
            x = tr.x.reshape(-1, p.order)
            _VISITED.setdefault(p, {})[a, float(duration)] = (
                np.abs(tr.x).max(axis=(0, 1)),
                x.T @ x / len(x),
            )
    return [_VISITED[p][float(a), float(duration)][0].copy() for p, a in requests]


def family_references(
    plant: Plant, spec: Mapping[str, Any], steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """References (B, steps) and initial states (B, n) of one family for ``plant``.

    A share ``x0_fraction`` of the initial states is random (``x0_draw``, the module's note).

    Raises
    ------
    ValueError
        An unknown ``kind`` or a malformed range.
    """
    spec = family_spec(spec, extra=("duration", "plants", "perturbation"))
    rng = np.random.default_rng(int(spec["seed"]) + 1000 * plant.tag)
    t = np.arange(steps) * plant.dt
    r = FAMILIES[spec["kind"]](spec, t, rng) * plant.amplitude_scale
    amplitude = float(spec["x0_amplitude"])
    if spec["x0_draw"] == "box":
        x0 = rng.uniform(-1.0, 1.0, size=(r.shape[0], plant.order)) * float(spec["x0_scale"])
        x0 *= state_envelope(plant, amplitude)
    else:  # a Gaussian with the visited states' second moment: coordinate-free
        root = visited_root(plant, amplitude) * float(spec["x0_scale"])
        x0 = rng.standard_normal((r.shape[0], plant.order)) @ root.T
    x0[int(round(float(spec["x0_fraction"]) * r.shape[0])) :] = 0.0
    return r, x0
