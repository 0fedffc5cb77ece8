"""Plant variants in the data stage (``data.variants``, a switch, off by default).

With ``data.variants.enabled``, every plant gets ``count`` variants fit for LQI
(:func:`generalist_control.simulation.variant_sampling.sample_variants`, seeded by ``seed`` and the
plant's tag; ranges from ``range`` and the plant file's ``variants`` block), each tracked by
its own LQI expert designed with the plant's ``Q`` and ``R``. The data size stays that of the
nominal set: the plant's trajectories, in the order they are generated (the step grid, then
each family), are dealt round-robin to the nominal plant (slot 0) and its variants (slots
1..count): trajectory ``j`` runs on slot ``j mod (count + 1)``. The references and initial
states are those of the nominal data. Each trajectory's slot is the dataset's ``variant``
column; the tag stays the nominal plant's. The manifest records every kept variant's
parameters and factors and every rejected candidate with its reason.

Off, nothing changes: neither the ``variant`` column nor the disabled keys (``data.variants``,
the plant files' ``variants`` blocks) reach the data or its content hash.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from generalist_control.common.schema import require_int
from generalist_control.plants.definition import Plant
from generalist_control.plants.variants import variant_range
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import Trajectory, simulate
from generalist_control.simulation.variant_sampling import VariantDraw, sample_variants

__all__ = [
    "assign_slots",
    "hashed_config",
    "simulate_assigned",
    "training_variants",
    "variants_config",
]


def variants_config(data: Mapping[str, Any]) -> dict[str, Any] | None:
    """The checked ``data.variants`` block, or None when it is absent or disabled.

    Raises
    ------
    ValueError
        A count below 1, a range outside (0, 1), a non-integer seed or max_tries.
    """
    block = dict(data.get("variants") or {})
    if not block or not block["enabled"]:
        return None
    missing = sorted({"count", "seed", "max_tries", "range"} - set(block))
    if missing:
        raise ValueError(f"data.variants needs {missing} (conf/data/demos.yaml has them all)")
    count = require_int("data.variants.count", block["count"])
    seed = require_int("data.variants.seed", block["seed"], minimum=0)
    tries = require_int("data.variants.max_tries", block["max_tries"])
    rng = variant_range(block["range"], "data.variants.range")
    if count < 1 or tries < 1:
        raise ValueError("data.variants.count and data.variants.max_tries must be at least 1")
    return {"count": count, "seed": seed, "range": rng, "max_tries": tries}


def hashed_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """``config`` without the variant keys when variants are off (they change nothing then)."""
    out = copy.deepcopy(dict(config))
    data = out.get("data") or {}
    if variants_config(data) is not None:
        return out
    data.pop("variants", None)
    for plant in ((out.get("systems") or {}).get("plants") or {}).values():
        if isinstance(plant, dict):
            plant.pop("variants", None)
    return out


def training_variants(
    plants: Sequence[Plant], vcfg: Mapping[str, Any], grid: np.ndarray, steps: int
) -> dict[str, VariantDraw]:
    """Each plant's variants; each must hold the grid's largest steps (both signs)."""
    top = float(np.abs(grid).max())
    return {
        p.name: sample_variants(
            p, vcfg["count"], vcfg["seed"], vcfg["range"], (top, -top), steps, vcfg["max_tries"]
        )
        for p in plants
    }


def assign_slots(n: int, count: int, start: int) -> np.ndarray:
    """Slots (0: nominal, 1..count: variants) of trajectories ``start .. start + n - 1``."""
    return (start + np.arange(n)) % (count + 1)


def simulate_assigned(
    draw: VariantDraw,
    ctrl: LQIController,
    r: np.ndarray,
    x0: np.ndarray | None,
    start: int,
) -> tuple[Trajectory, np.ndarray]:
    """Run each row of ``r`` on its slot's plant with that plant's LQI; rows keep their order.

    Returns the trajectories (stacked as one) and each row's slot.
    """
    slots = assign_slots(len(r), len(draw.kept), start)
    plants = [(draw.nominal, ctrl)] + [(v.plant, LQIController(v.plant)) for v in draw.kept]
    n, steps = draw.nominal.order, r.shape[1]
    x = np.zeros((len(r), steps + 1, n))
    y, u = np.zeros((len(r), steps + 1)), np.zeros((len(r), steps))
    diverged = np.zeros(len(r), bool)
    for slot, (plant, c) in enumerate(plants):
        rows = np.flatnonzero(slots == slot)
        if rows.size:
            tr = simulate(plant, c, r[rows], None if x0 is None else x0[rows])
            x[rows], y[rows], u[rows], diverged[rows] = tr.x, tr.y, tr.u, tr.diverged
    t = np.arange(steps + 1) * draw.nominal.dt
    return Trajectory(t=t, x=x, u=u, r=r, y=y, diverged=diverged), slots
