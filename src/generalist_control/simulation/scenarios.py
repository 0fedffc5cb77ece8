"""Evaluation scenarios (``conf/evaluation/*.yaml``): references, initial states, perturbations.

Amplitudes are scaled by each plant's ``amplitude_scale``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from generalist_control.plants.definition import Plant
from generalist_control.simulation.perturbation import Perturbation
from generalist_control.simulation.references import (
    FAMILIES,
    X0_DRAWS,
    family_references,
    family_spec,
    state_envelope,
    visited_root,
)

__all__ = [
    "KINDS",
    "ScenarioError",
    "envelope_amplitudes",
    "perturbation",
    "references",
    "runs_on",
    "with_state_draw",
]

#: Each scenario kind's parameters and their defaults, the one place they live.
PARAMETERS: dict[str, dict[str, Any]] = {
    "step": {"amplitude": 1.0},
    "random_steps": {"count": 8, "limit": 20.0, "seed": 0},
    "sine": {"amplitude": 1.0, "omega": 0.5, "y0": 0.5},
    "ramp": {"slope": 0.2},
    "composite": {"amplitude": 1.0, "omega": 1.0},
}
#: What every scenario takes beside its kind's parameters.
SCENARIO = {"duration": 15.0, "plants": None, "perturbation": None}
KINDS = (*PARAMETERS, *FAMILIES)


class ScenarioError(ValueError):
    """An evaluation scenario is misconfigured; the message names the field."""


def runs_on(spec: Mapping[str, Any], plant: str) -> bool:
    """Whether scenario ``spec`` runs on ``plant``: those its ``plants`` lists, else every one.

    ``plants: []`` lists none: the scenario runs on no plant.
    """
    return spec.get("plants") is None or plant in spec["plants"]


def references(
    name: str, spec: Mapping[str, Any], plant: Plant
) -> tuple[np.ndarray, np.ndarray | None]:
    """Reference signals ``(B, N)`` and initial states ``(B, n)`` (or None: rest).

    ``composite``: a step to ``amplitude`` for the first third, a ramp to ``3 * amplitude``
    over the second, then a sine of amplitude ``amplitude`` about it. ``sine`` starts from a
    state with output ``y0``; the other kinds but the families start from rest.
    """
    spec = scenario_spec(name, spec)
    kind, duration = spec["kind"], float(spec["duration"])
    steps = int(round(duration / plant.dt))
    if steps < 2:
        raise ScenarioError(f"scenario '{name}': duration {duration} s is too short")
    if kind in FAMILIES:
        return family_references(plant, spec, steps)
    t = np.arange(steps) * plant.dt
    scale = plant.amplitude_scale
    amp = float(spec["amplitude"]) * scale if "amplitude" in spec else 0.0
    x0 = None
    if kind == "step":
        r = np.full((1, steps), amp)
    elif kind == "random_steps":
        rng = np.random.default_rng(int(spec["seed"]) + 1000 * plant.tag)
        limit = float(spec["limit"]) * scale
        amps = rng.uniform(-limit, limit, size=int(spec["count"]))
        r = np.repeat(amps[:, None], steps, axis=1)
    elif kind == "sine":
        r = amp * np.sin(float(spec["omega"]) * t)[None, :]
        c = plant.C[0]  # the smallest state whose output is y0
        x0 = (float(spec["y0"]) * scale * c / (c @ c))[None, :]
    elif kind == "ramp":
        r = (float(spec["slope"]) * scale * t)[None, :]
    else:  # composite
        third = t[-1] / 3
        ramp = amp + 2 * amp * np.clip((t - third) / third, 0, 1)
        sine = np.where(t > 2 * third, amp * np.sin(float(spec["omega"]) * (t - 2 * third)), 0)
        r = np.where(t < third, amp, ramp + sine)[None, :]
    return r, x0


def scenario_spec(name: str, spec: Mapping[str, Any]) -> dict[str, Any]:
    """``spec`` with its kind's defaults filled in (:data:`PARAMETERS`, :data:`SCENARIO`).

    Raises
    ------
    ScenarioError
        An unknown kind, or a key its kind does not take (naming the scenario).
    """
    kind = spec.get("kind")
    if kind not in KINDS:
        raise ScenarioError(f"scenario '{name}': kind '{kind}' is not one of {', '.join(KINDS)}")
    if kind in FAMILIES:
        try:
            return {**SCENARIO, **family_spec(spec, extra=tuple(SCENARIO))}
        except ValueError as exc:
            raise ScenarioError(f"scenario '{name}': {exc}") from exc
    unknown = sorted(set(spec) - set(PARAMETERS[kind]) - set(SCENARIO) - {"kind"})
    if unknown:
        raise ScenarioError(
            f"scenario '{name}': {unknown} are not parameters of a '{kind}' scenario: "
            f"{sorted({*PARAMETERS[kind], *SCENARIO})}"
        )
    return {**SCENARIO, **PARAMETERS[kind], **spec}


def with_state_draw(
    scenarios: Mapping[str, Mapping[str, Any]], draw: str
) -> dict[str, Mapping[str, Any]]:
    """``scenarios`` whose random states (initial states, relative noise) are drawn by ``draw``."""
    out: dict[str, Mapping[str, Any]] = {}
    for name, spec in scenarios.items():
        noise = dict(spec.get("perturbation") or {})
        if "noise_rel" in noise:
            spec = {**spec, "perturbation": {**noise, "noise_draw": draw}}
        out[name] = {**spec, "x0_draw": draw} if spec["kind"] in FAMILIES else spec
    return out


def envelope_amplitudes(name: str, spec: Mapping[str, Any]) -> list[float]:
    """The step amplitudes of the state envelopes the scenario's runs ask for."""
    spec = scenario_spec(name, spec)
    out = [float(spec["x0_amplitude"])] if spec["kind"] in FAMILIES else []
    if (spec["perturbation"] or {}).get("noise_rel") is not None:
        out.append(1.0)
    return out


def perturbation(
    name: str, spec: Mapping[str, Any], plant: Plant | None = None
) -> Perturbation | None:
    """The scenario's :class:`~generalist_control.simulation.perturbation.Perturbation`, if any.

    ``noise_rel`` (with ``plant``): ``noise_std`` as that fraction of the unit-step envelope
    per state (``noise_draw: box``) or of the visited states' root (``visited``, any
    coordinates: :mod:`~generalist_control.simulation.references`).
    """
    fields = dict(spec.get("perturbation") or {})
    if not fields:
        return None
    rel, draw = fields.pop("noise_rel", None), fields.pop("noise_draw", "box")
    if draw not in X0_DRAWS:
        raise ScenarioError(f"scenario '{name}': noise_draw must be one of {', '.join(X0_DRAWS)}")
    if rel is not None:
        if plant is None:
            raise ScenarioError(f"scenario '{name}': noise_rel needs the plant")
        if draw == "box":
            fields["noise_std"] = tuple(float(rel) * state_envelope(plant, 1.0))
        else:
            fields["noise_std"] = tuple(map(tuple, float(rel) * visited_root(plant, 1.0)))
    kwargs: dict[str, Any] = {
        k: (tuple(v) if isinstance(v, list) else v) for k, v in fields.items()
    }
    try:
        return Perturbation(**kwargs)
    except TypeError as exc:
        raise ScenarioError(f"scenario '{name}': bad perturbation field ({exc})") from exc
