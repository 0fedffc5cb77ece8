"""Plant variants in the data stage (``data.variants``, off by default).

A plant's trajectories are dealt round-robin to the nominal plant (slot 0) and its ``count``
variants, each with its own LQI expert; off, nothing reaches the data or its hash.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from generalist_control.common.sections import require_int
from generalist_control.plants.definition import Plant
from generalist_control.plants.variants import variant_range
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import Trajectory, simulate
from generalist_control.simulation.variant_sampling import VariantDraw, sample_variants

__all__ = [
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
        Naming the bad key.
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


def simulate_assigned(
    draw: VariantDraw,
    ctrl: LQIController,
    r: np.ndarray,
    x0: np.ndarray | None,
    start: int,
) -> tuple[Trajectory, np.ndarray]:
    """Row ``j`` of ``r`` run on slot ``(start + j) mod (count + 1)``; trajectories and slots."""
    slots = (start + np.arange(len(r))) % (len(draw.kept) + 1)
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
