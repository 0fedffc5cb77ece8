"""Evaluation scenarios (``conf/evaluation/*.yaml``): references, initial states, perturbations.

A scenario names its ``kind`` (:data:`KINDS`), ``duration``, optional ``plants`` and
``perturbation`` (fields of :class:`~generalist_control.simulation.simulate.Perturbation`,
plus ``noise_rel``: noise relative to the plant's state envelope), and its kind's parameters.
Amplitudes are scaled by each plant's ``amplitude_scale``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from generalist_control.plants.plant import Plant
from generalist_control.simulation.references import (
    FAMILIES,
    family_references,
    state_envelope,
)
from generalist_control.simulation.simulate import Perturbation

__all__ = ["KINDS", "ScenarioError", "envelope_amplitudes", "perturbation", "references"]

KINDS = ("step", "random_steps", "sine", "ramp", "composite", *FAMILIES)


class ScenarioError(ValueError):
    """An evaluation scenario is misconfigured; the message names the field."""


def _x0_for_output(plant: Plant, y0: float, batch: int) -> np.ndarray:
    """The smallest state (deviation) whose output is ``y0``."""
    c = plant.C[0]
    return np.repeat((y0 * c / (c @ c))[None, :], batch, axis=0)


def references(
    name: str, spec: Mapping[str, Any], plant: Plant
) -> tuple[np.ndarray, np.ndarray | None]:
    """Reference signals ``(B, N)`` and initial states ``(B, n)`` (or None: rest).

    Kinds and their parameters:

    - ``step``: ``amplitude`` (default 1), a step at t = 0 from rest;
    - ``random_steps``: ``count`` steps from rest with amplitudes uniform in ``+-limit``
      (drawn with ``seed``; a continuous draw lies off the training grid almost surely);
    - ``sine``: ``amplitude * sin(omega t)`` from an initial state with output ``y0``;
    - ``ramp``: ``slope * t`` from rest;
    - ``composite``: a step to ``amplitude`` for the first third, a ramp to
      ``3 * amplitude`` over the second, then a sine of amplitude ``amplitude`` about it;
    - a family of :mod:`~generalist_control.simulation.references` (random references and
      initial states).
    """
    kind = spec.get("kind")
    if kind not in KINDS:
        raise ScenarioError(f"scenario '{name}': kind '{kind}' is not one of {', '.join(KINDS)}")
    duration = float(spec.get("duration", 15.0))
    steps = int(round(duration / plant.dt))
    if steps < 2:
        raise ScenarioError(f"scenario '{name}': duration {duration} s is too short")
    if kind in FAMILIES:
        try:
            return family_references(plant, spec, steps)
        except ValueError as exc:
            raise ScenarioError(f"scenario '{name}': {exc}") from exc
    t = np.arange(steps) * plant.dt
    scale = plant.amplitude_scale
    amp = float(spec.get("amplitude", 1.0)) * scale
    x0 = None
    if kind == "step":
        r = np.full((1, steps), amp)
    elif kind == "random_steps":
        rng = np.random.default_rng(int(spec.get("seed", 0)) + 1000 * plant.tag)
        limit = float(spec.get("limit", 20.0)) * scale
        amps = rng.uniform(-limit, limit, size=int(spec.get("count", 8)))
        r = np.repeat(amps[:, None], steps, axis=1)
    elif kind == "sine":
        omega = float(spec.get("omega", 0.5))
        r = amp * np.sin(omega * t)[None, :]
        x0 = _x0_for_output(plant, float(spec.get("y0", 0.5)) * scale, 1)
    elif kind == "ramp":
        r = (float(spec.get("slope", 0.2)) * scale * t)[None, :]
    else:  # composite
        third = t[-1] / 3
        ramp = amp + 2 * amp * np.clip((t - third) / third, 0, 1)
        sine = np.where(
            t > 2 * third, amp * np.sin(float(spec.get("omega", 1.0)) * (t - 2 * third)), 0
        )
        r = np.where(t < third, amp, ramp + sine)[None, :]
    return r, x0


def envelope_amplitudes(spec: Mapping[str, Any]) -> list[float]:
    """The step amplitudes of the state envelopes the scenario's runs ask for.

    A family's random initial states (``x0_amplitude``) and ``noise_rel`` (unit steps);
    :func:`~generalist_control.simulation.references.state_envelopes` computes them for
    many plants at once beforehand.
    """
    out = [float(spec.get("x0_amplitude", 3.0))] if spec.get("kind") in FAMILIES else []
    if (spec.get("perturbation") or {}).get("noise_rel") is not None:
        out.append(1.0)
    return out


def perturbation(
    name: str, spec: Mapping[str, Any], plant: Plant | None = None
) -> Perturbation | None:
    """The scenario's :class:`~generalist_control.simulation.simulate.Perturbation`, if any.

    ``noise_rel`` (with ``plant``) sets ``noise_std`` to that fraction of the plant's state
    envelope for unit steps, so one scenario means the same on plants of any scale.
    """
    fields = dict(spec.get("perturbation") or {})
    if not fields:
        return None
    rel = fields.pop("noise_rel", None)
    if rel is not None:
        if plant is None:
            raise ScenarioError(f"scenario '{name}': noise_rel needs the plant")
        fields["noise_std"] = tuple(float(rel) * state_envelope(plant, 1.0))
    kwargs: dict[str, Any] = {
        k: (tuple(v) if isinstance(v, list) else v) for k, v in fields.items()
    }
    try:
        return Perturbation(**kwargs)
    except TypeError as exc:
        raise ScenarioError(f"scenario '{name}': bad perturbation field ({exc})") from exc
