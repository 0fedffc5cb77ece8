"""Randomised reference families and random initial states, for data, DAgger and evaluation.

One implementation for the data stage's families, DAgger's rollouts and the evaluation's
scenarios. Draws come from ``default_rng(seed + 1000 * plant.tag)``; amplitudes, levels and
slopes are scaled by ``plant.amplitude_scale``. A random initial state lies within the
plant's :func:`state_envelope`: a state it visits in operation, never an arbitrary one.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from generalist_control.plants.plant import Plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import PerPlantController, Run
from generalist_control.simulation.stacked import Segment, simulate_stacked

__all__ = [
    "FAMILIES",
    "family_references",
    "random_initial_states",
    "state_envelope",
    "state_envelopes",
]


def _range(spec: Mapping[str, Any], key: str, default: tuple[float, float]) -> tuple[float, float]:
    value = spec.get(key, default)
    if isinstance(value, int | float):
        return float(value), float(value)
    lo, hi = (float(v) for v in value)
    if hi < lo:
        raise ValueError(f"'{key}' must be [low, high] with low <= high, got {list(value)}")
    return lo, hi


def _staircase(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, limit = int(spec.get("count", 8)), float(spec.get("limit", 10.0))
    lo, hi = _range(spec, "levels", (2, 4))
    r = np.empty((count, len(t)))
    for b in range(count):
        n = int(rng.integers(int(lo), int(hi) + 1))
        levels = rng.uniform(-limit, limit, size=n)
        r[b] = levels[np.minimum((np.arange(len(t)) * n) // len(t), n - 1)]
    return r


def _sines(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, offset = int(spec.get("count", 8)), float(spec.get("offset", 2.0))
    amp = rng.uniform(*_range(spec, "amplitude", (0.2, 3.0)), size=(count, 1))
    w_lo, w_hi = _range(spec, "omega", (0.2, 3.0))
    omega = np.exp(rng.uniform(np.log(w_lo), np.log(w_hi), size=(count, 1)))
    phase = rng.uniform(0.0, 2 * np.pi, size=(count, 1))
    c = rng.uniform(-offset, offset, size=(count, 1))
    return c + amp * np.sin(omega * t[None, :] + phase)


def _sweep(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, offset = int(spec.get("count", 1)), float(spec.get("offset", 0.0))
    amp = rng.uniform(*_range(spec, "amplitude", (1.0, 1.0)), size=(count, 1))
    w0, w1 = _range(spec, "omega", (0.1, 2.0))
    phase = rng.uniform(0.0, 2 * np.pi, size=(count, 1)) if count > 1 else np.zeros((1, 1))
    c = rng.uniform(-offset, offset, size=(count, 1))
    span = max(float(t[-1]), 1e-12)
    angle = w0 * t + 0.5 * (w1 - w0) * t**2 / span  # instantaneous frequency w0 -> w1
    return c + amp * np.sin(angle[None, :] + phase)


def _ramps(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, offset = int(spec.get("count", 6)), float(spec.get("offset", 2.0))
    slope = rng.uniform(*_range(spec, "slope", (0.05, 1.0)), size=(count, 1))
    slope *= rng.choice([-1.0, 1.0], size=(count, 1))
    c = rng.uniform(-offset, offset, size=(count, 1))
    return c + slope * t[None, :]


def _hold(spec: Mapping[str, Any], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    count, limit = int(spec.get("count", 8)), float(spec.get("limit", 5.0))
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


#: Envelopes per plant (plants are immutable; a dropped plant drops its entries).
_ENVELOPES: weakref.WeakKeyDictionary[Plant, dict[tuple[float, float], np.ndarray]] = (
    weakref.WeakKeyDictionary()
)


def state_envelope(plant: Plant, amplitude: float = 3.0, duration: float = 10.0) -> np.ndarray:
    """Largest ``|x_i|`` (n,) along the LQI expert's responses to steps of ``+-amplitude``.

    ``amplitude`` is scaled by the plant's ``amplitude_scale``; cached per plant.
    """
    return state_envelopes([(plant, amplitude)], duration)[0]


def state_envelopes(
    requests: Sequence[tuple[Plant, float]], duration: float = 10.0
) -> list[np.ndarray]:
    """:func:`state_envelope` of many ``(plant, amplitude)``, the missing ones in one loop."""
    missing = list(dict.fromkeys(
        (p, float(a)) for p, a in requests
        if (float(a), float(duration)) not in _ENVELOPES.get(p, {})
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
            _ENVELOPES.setdefault(p, {})[a, float(duration)] = np.abs(tr.x).max(axis=(0, 1))
    return [_ENVELOPES[p][float(a), float(duration)].copy() for p, a in requests]


def random_initial_states(
    plant: Plant, spec: Mapping[str, Any], count: int, rng: np.random.Generator
) -> np.ndarray:
    """Initial states (count, n): a share ``x0_fraction`` random within the envelope."""
    default = 1.0 if spec.get("kind") == "hold" else 0.0
    fraction = float(spec.get("x0_fraction", default))
    env = state_envelope(plant, float(spec.get("x0_amplitude", 3.0)))
    x0 = rng.uniform(-1.0, 1.0, size=(count, plant.order)) * float(spec.get("x0_scale", 1.0))
    x0 *= env
    x0[int(round(fraction * count)) :] = 0.0
    return x0


def family_references(
    plant: Plant, spec: Mapping[str, Any], steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """References (B, steps) and initial states (B, n) of one family for ``plant``.

    Raises
    ------
    ValueError
        An unknown ``kind`` or a malformed range.
    """
    kind = spec.get("kind")
    if kind not in FAMILIES:
        raise ValueError(f"family kind '{kind}' is not one of {', '.join(FAMILIES)}")
    rng = np.random.default_rng(int(spec.get("seed", 0)) + 1000 * plant.tag)
    t = np.arange(steps) * plant.dt
    r = FAMILIES[kind](spec, t, rng) * plant.amplitude_scale
    return r, random_initial_states(plant, spec, r.shape[0], rng)
