"""The demonstrations: every plant's LQI expert on the step grid and on richer families.

The paper's are steps from rest on the amplitude grid (family ``steps``); ``data.families``
adds reference families (:mod:`generalist_control.simulation.references`). ``data.variants``
(off by default) deals a plant's trajectories round-robin to the nominal plant (slot 0) and its
variants, each with its own LQI expert; off, nothing reaches the data or its hash.
"""

from __future__ import annotations

import copy
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from generalist_control import __version__
from generalist_control.common.sections import require_int
from generalist_control.data.demos import FORMAT_VERSION, DemoSet, content_hash
from generalist_control.data.windows import windows_per_trajectory
from generalist_control.plants.definition import MAX_ORDER, Plant, pad_states
from generalist_control.plants.variants import variant_range
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.references import FAMILIES, family_references
from generalist_control.simulation.simulate import simulate
from generalist_control.simulation.variant_sampling import VariantDraw, sample_variants

__all__ = [
    "STEPS",
    "DataConfigError",
    "amplitude_grid",
    "build_manifest",
    "enabled_families",
    "generate_demos",
    "training_variants",
    "variants_config",
]

#: The family of the paper's steps from rest on the amplitude grid.
STEPS = "steps"


class DataConfigError(ValueError):
    """The ``data`` config is invalid; the message names the field."""


def amplitude_grid(amplitudes: Mapping[str, Any]) -> np.ndarray:
    """The sorted step-amplitude grid of the ``data.amplitudes`` node, without zero.

    Each segment ``{start, stop, step}`` gives ``start, start + step, ..., stop``;
    ``symmetric`` adds the negatives.

    Raises
    ------
    DataConfigError
        If a segment is malformed or reaches outside ``+-limit``.
    """
    limit = float(amplitudes["limit"])
    values: list[np.ndarray] = []
    segments = amplitudes["segments"] or []
    if not segments:
        raise DataConfigError("data.amplitudes.segments is empty: give at least one segment")
    for i, seg in enumerate(segments):
        field = f"data.amplitudes.segments[{i}]"
        try:
            start, stop, step = (float(seg[k]) for k in ("start", "stop", "step"))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataConfigError(f"{field} needs numeric 'start', 'stop' and 'step'") from exc
        if not step > 0:
            raise DataConfigError(f"{field}.step must be positive, got {step}")
        if stop < start:
            raise DataConfigError(f"{field}.stop ({stop}) is below its start ({start})")
        for key, v in (("start", start), ("stop", stop)):
            if abs(v) > limit:
                raise DataConfigError(
                    f"{field}.{key} = {v} lies outside the amplitude limit +-{limit} "
                    "(data.amplitudes.limit)"
                )
        count = int(np.floor((stop - start) / step + 1e-9)) + 1
        values.append(np.round(start + step * np.arange(count), 10))
    grid = np.concatenate(values)
    if amplitudes["symmetric"]:
        grid = np.concatenate([grid, -grid])
    grid = np.unique(grid[grid != 0.0])
    return grid


def _steps(data: Mapping[str, Any], plants: Sequence[Plant]) -> tuple[float, int]:
    """The plants' common sample time and the samples per trajectory."""
    dts = {p.dt for p in plants}
    if len(dts) != 1:
        raise DataConfigError(
            "plants of one set must share a sample time; got "
            + ", ".join(f"{p.name}: {p.dt}" for p in plants)
        )
    dt = dts.pop()
    history, horizon = int(data["history"]), int(data["horizon"])
    if history < 1 or horizon < 1:
        raise DataConfigError("data.history and data.horizon must be at least 1")
    steps = int(round(float(data["duration"]) / dt))
    if steps < horizon + 1:
        raise DataConfigError(
            f"data.duration = {data['duration']} s gives {steps} samples at dt = {dt} s; "
            f"need more than data.horizon = {horizon}"
        )
    return dt, steps


def enabled_families(data: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The enabled demonstration families of ``data.families`` (name -> family spec).

    Raises
    ------
    DataConfigError
        A family without a known ``kind``.
    """
    out = {}
    for name, spec in (data.get("families") or {}).items():
        spec = dict(spec or {})
        if not spec.pop("enabled", True):
            continue
        if spec.get("kind") not in FAMILIES:
            raise DataConfigError(
                f"data.families.{name}.kind = {spec.get('kind')!r} is not one of "
                f"{', '.join(FAMILIES)}"
            )
        out[str(name)] = spec
    return out


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
    return {"count": count, "seed": seed, "range": rng, "max_tries": tries}


def _hashed_config(config: Mapping[str, Any], variants: bool) -> dict[str, Any]:
    """``config`` without the variant keys when ``variants`` are off (they change nothing then)."""
    out = copy.deepcopy(dict(config))
    if variants:
        return out
    (out.get("data") or {}).pop("variants", None)
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


def _plant_runs(
    plant: Plant, grid: np.ndarray, families: Mapping[str, Mapping[str, Any]], steps: int
) -> list[tuple[str, np.ndarray, np.ndarray | None]]:
    """``(family, references, initial states)`` of every trajectory of one plant."""
    amp = grid * plant.amplitude_scale
    runs: list[tuple[str, np.ndarray, np.ndarray | None]] = [
        (STEPS, np.repeat(amp[:, None], steps, axis=1), None)
    ]
    for name, spec in families.items():
        try:
            r, x0 = family_references(plant, spec, steps)
        except ValueError as exc:
            raise DataConfigError(f"data.families.{name}: {exc}") from exc
        runs.append((name, r, x0))
    return runs


def _run(
    plant: Plant,
    ctrl: LQIController,
    draw: VariantDraw | None,
    family: str,
    r: np.ndarray,
    x0: np.ndarray | None,
    done: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One family's runs of a plant: states, controls, outputs and each run's slot.

    Row ``j`` runs on slot ``(done + j) mod (variants + 1)``: the plant (0) or one of its variants.
    """
    variants = [(v.plant, LQIController(v.plant)) for v in draw.kept] if draw else []
    slots = (done + np.arange(len(r))) % (len(variants) + 1)
    x, u = np.zeros((len(r), r.shape[1] + 1, plant.order)), np.zeros(r.shape)
    y, diverged = np.zeros((len(r), r.shape[1] + 1)), np.zeros(len(r), bool)
    for slot, (version, c) in enumerate([(plant, ctrl), *variants]):
        rows = np.flatnonzero(slots == slot)
        if rows.size:
            tr = simulate(version, c, r[rows], None if x0 is None else x0[rows])
            x[rows], y[rows], u[rows], diverged[rows] = tr.x, tr.y, tr.u, tr.diverged
    if diverged.any():
        which = sorted({int(v) for v in slots[diverged]})
        raise RuntimeError(
            f"plant '{plant.name}': LQI closed loop diverged in the data stage "
            f"(family '{family}'" + (f", variants {which})" if draw else ")")
        )
    return x, u, y, slots


def generate_demos(
    plants: Sequence[Plant], data: Mapping[str, Any], progress: bool | None = None
) -> DemoSet:
    """Simulate every plant's LQI expert on the amplitude grid and on every family of ``data``.

    With ``data.variants`` enabled, trajectories are dealt to the plant and its variants
    (:func:`variants_config`). ``progress`` None: a bar on a terminal.
    """
    grid = amplitude_grid(data["amplitudes"])
    families = enabled_families(data)
    dt, steps = _steps(data, plants)
    controllers = [LQIController(p, design_lqi(p)) for p in plants]  # validates all first
    vcfg = variants_config(data)
    draws = training_variants(plants, vcfg, grid, steps) if vcfg else None
    parts = []
    disable = None if progress is None else not progress
    pairs = tqdm(
        list(zip(plants, controllers, strict=True)),
        desc="generate", unit="plant", disable=disable, file=sys.stderr,
    )  # fmt: skip
    for plant, ctrl in pairs:
        done = 0
        for family, r, x0 in _plant_runs(plant, grid, families, steps):
            draw = None if draws is None else draws[plant.name]
            x, u, y, slots = _run(plant, ctrl, draw, family, r, x0, done)
            done += len(r)
            fam, tag = np.full(len(r), family), np.full(len(r), plant.tag)
            parts.append((pad_states(x[:, :steps]), r, u, y[:, :steps], fam, tag, slots))
    x, r, u, y, fam, tags, slots = (np.concatenate(c) for c in zip(*parts, strict=True))
    tags = tags.astype(np.int64)
    by_tag = {p.tag: p for p in plants}
    return DemoSet(
        x=x,
        r=r,
        u=u,
        y=y,
        tag=tags,
        order=np.array([by_tag[t].order for t in tags], dtype=np.int64),
        plant=np.array([by_tag[t].name for t in tags]),
        amplitude=r[:, -1].copy(),
        dt=dt,
        family=fam,
        variant=slots.astype(np.int64) if draws else None,
    )


def build_manifest(
    plants: Sequence[Plant], demos: DemoSet, data: Mapping[str, Any], config: dict[str, Any]
) -> dict[str, Any]:
    """The manifest: window counts, per-plant facts, the resolved config and content hash.

    With ``data.variants`` enabled, also each plant's variants (drawn again) and rejections.
    """
    vcfg = variants_config(data)
    config = _hashed_config(config, vcfg is not None)
    history, horizon = int(data["history"]), int(data["horizon"])
    steps = demos.r.shape[1]
    per_traj = windows_per_trajectory(steps, horizon)
    n_traj = {p.name: int(np.sum(demos.plant == p.name)) for p in plants}
    fams = {str(f): int(np.sum(demos.family == f)) for f in dict.fromkeys(demos.family.tolist())}
    extra = {}
    if vcfg is not None:
        draws = training_variants(plants, vcfg, amplitude_grid(data["amplitudes"]), steps)
        extra = {"variants": {name: d.record() for name, d in draws.items()}}
    return {
        **extra,
        "format_version": FORMAT_VERSION,
        "generator": f"generalist_control {__version__}",
        "n_demonstrations": per_traj * len(demos.r),
        "n_trajectories": len(demos.r),
        "steps_per_trajectory": steps,
        "windows_per_trajectory": per_traj,
        "dt": demos.dt,
        "history": history,
        "horizon": horizon,
        "max_order": MAX_ORDER,
        "plants": {
            p.name: {
                "tag": p.tag,
                "order": p.order,
                "linear": p.is_linear,
                "amplitude_scale": p.amplitude_scale,
                "n_trajectories": n_traj[p.name],
                "n_demonstrations": n_traj[p.name] * per_traj,
            }
            for p in plants
        },
        "families": {
            f: {"n_trajectories": n, "n_demonstrations": n * per_traj} for f, n in fams.items()
        },
        "config": config,
        "content_hash": content_hash(demos, config),
    }
