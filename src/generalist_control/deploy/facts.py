"""What a policy's runtime needs to know of each catalogue plant beyond the policy itself.

An integrating policy's runtime integrates ``r - C x`` from the state alone and, under
actuator limits, must know which way the integral moves the command (anti-windup).
Training stores these facts in the policy's meta; the runtime falls back to this
function for plants the meta lacks.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.simulation.lqi import design_lqi

__all__ = ["integral_facts"]


def integral_facts(names: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Per catalogue plant in ``names``, its output row ``C`` and the sign of its expert's -Ki.

    What an integrating policy's runtime needs to integrate ``r - C x`` from the state alone
    (``C`` of the linearisation for a nonlinear plant) and to know which way the integral
    moves the command (anti-windup). Training stores them in the policy's meta
    (``outputs``, ``integral_directions``); names the catalogue does not know are left out.
    """
    known = set(available_plants())
    plants = [load_plant(n) for n in sorted(names) if n in known]
    return {
        "outputs": {p.name: [float(c) for c in p.C[0]] for p in plants},
        "integral_directions": {p.name: float(np.sign(-design_lqi(p).Ki)) for p in plants},
    }
