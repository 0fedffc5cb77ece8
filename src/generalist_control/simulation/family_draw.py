"""Drawing a family's plants fit for their LQI experts, each refusal with its reason.

The checks run in the order of :data:`REASONS` (docs/notes/plant-families.md); the kept plants
are the first ``count`` candidates that pass, tagged ``0 .. count - 1``.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from hydra.utils import instantiate
from threadpoolctl import threadpool_limits

from generalist_control.common.sections import read_section
from generalist_control.plants.definition import Plant, PlantConfigError
from generalist_control.plants.families import Candidate, PlantFamily
from generalist_control.simulation.lqi import LQIGains, design_lqi, sampled_closed_loop

__all__ = [
    "REASONS",
    "DrawnPlant",
    "FamilyChecks",
    "FamilyDraw",
    "FamilySettings",
    "Rejected",
    "check_design",
    "draw_family",
    "read_families",
    "settling_times",
]

#: Why a candidate is refused, in the order the checks run: a bandwidth for the weights, the
#: LQI design, ``|s| dt <= max_pole_dt`` of the fastest pole, settling within the fraction.
REASONS = (
    "no_bandwidth",
    "zero_at_origin",
    "not_stabilisable",
    "design_failed",
    "sampled_unstable",
    "too_fast",
    "too_slow",
)
#: Band of the settling time around the final value.
SETTLE_BAND = 0.02


class Rejected(ValueError):
    """A candidate refused: ``reason`` (one of :data:`REASONS`) and the message."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason, self.message = reason, message


@dataclass(frozen=True)
class FamilyChecks:
    """``families.checks``: what a drawn plant's LQI loop must do (every field from config)."""

    max_pole_dt: float
    settle_fraction: float
    duration: float
    max_tries: int

    def __post_init__(self) -> None:
        if not (0 < self.max_pole_dt < math.inf and 0 < self.settle_fraction <= 1):
            raise ValueError("families.checks: max_pole_dt must be > 0, settle_fraction in (0, 1]")
        if not self.duration > 0 or self.max_tries < 1:
            raise ValueError("families.checks: duration must be > 0 and max_tries >= 1")


@dataclass(frozen=True)
class FamilySettings:
    """A ``families`` config group (``conf/families/<name>.yaml``) but its generator."""

    checks: FamilyChecks
    count: int
    data_dir: str
    demos: Any


def read_families(node: Mapping[str, Any]) -> tuple[PlantFamily, FamilySettings]:
    """The family its ``generator`` block builds (``_target_``) and the group's settings.

    ``node`` is the group as plain types.

    Raises
    ------
    ValueError
        Naming the key: a generator that refuses its arguments, a bad check or count.
    """
    node = dict(node)
    generator = node.pop("generator", None)
    if not isinstance(generator, Mapping) or "_target_" not in generator:
        raise ValueError("families.generator must name a plant family (_target_)")
    settings = read_section(FamilySettings, node, "families")
    if settings.count < 1:
        raise ValueError(f"families.count must be at least 1, got {settings.count}")
    try:
        family = instantiate(generator)
    except Exception as exc:  # Hydra wraps the constructor's error
        raise ValueError(str(exc.__cause__ or exc)) from None
    return family, settings


@dataclass(frozen=True)
class DrawnPlant:
    """A kept plant (its tag: its place in the draw), its candidate, gains and settling time."""

    plant: Plant
    candidate: Candidate
    gains: LQIGains
    settling_time: float

    def record(self) -> dict[str, Any]:
        """The manifest's entry: the candidate's parameters, tag and settling time."""
        return {
            **self.candidate.record(),
            "tag": self.plant.tag,
            "settling_time": self.settling_time,
        }


_MESSAGES = (
    ("transmission zero at s = 0", "zero_at_origin"),
    ("not stabilisable", "not_stabilisable"),
    ("sampled at dt", "sampled_unstable"),
)


def check_design(plant: Plant, max_pole_dt: float) -> LQIGains:
    """``design_lqi(plant)`` and the fastest pole's check, or :class:`Rejected`."""
    try:
        gains = design_lqi(plant)
    except PlantConfigError as exc:
        reason = next((r for text, r in _MESSAGES if text in str(exc)), "design_failed")
        raise Rejected(reason, str(exc)) from None
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise Rejected("design_failed", f"the Riccati equation has no solution ({exc})") from None
    fastest = float(np.abs(gains.poles).max())
    if fastest * plant.dt > max_pole_dt:
        raise Rejected(
            "too_fast",
            f"closed-loop pole at {fastest:.4g} rad/s: |s| dt = {fastest * plant.dt:.3g} > "
            f"{max_pole_dt:g} (dt = {plant.dt} s does not resolve it)",
        )
    return gains


def settling_times(plants: Sequence[Plant], gains: Sequence[LQIGains], steps: int) -> np.ndarray:
    """2 % settling time of each sampled LQI loop's unit step from rest (inf: not settled).

    The loops are stacked, zero-padded to the largest augmented order, and stepped together.
    """
    size = max(p.order + p.C.shape[0] for p in plants)
    M = np.zeros((len(plants), size, size))
    out = np.zeros((len(plants), size))  # y = [C 0] s
    drive = np.zeros((len(plants), size))  # the reference enters the integrator: + dt r
    for i, (p, g) in enumerate(zip(plants, gains, strict=True)):
        m = p.order + p.C.shape[0]
        M[i, :m, :m] = sampled_closed_loop(p, g)
        out[i, : p.order] = p.C[0]
        drive[i, p.order : m] = p.dt
    s = np.zeros((len(plants), size))
    y = np.empty((len(plants), steps + 1))
    for k in range(steps + 1):
        y[:, k] = np.einsum("pi,pi->p", out, s)
        s = np.einsum("pij,pj->pi", M, s) + drive
    outside = ~(np.abs(y - 1.0) < SETTLE_BAND)
    last = steps - np.argmax(outside[:, ::-1], axis=1)  # last sample outside the band, + 1
    first_in = np.where(outside.any(axis=1), last + 1, 0)
    t = first_in * np.array([p.dt for p in plants])
    return np.where(first_in > steps, math.inf, t)


def _rejection(candidate: Candidate, reason: str, message: str) -> dict[str, Any]:
    """The manifest's record of a refused candidate."""
    return {"reason": reason, "message": message, **candidate.record(matrices=False)}


def _check_chunk(
    candidates: Sequence[Candidate], checks: FamilyChecks
) -> list[DrawnPlant | dict[str, Any]]:
    """Each candidate's verdict: a :class:`DrawnPlant` (tag not yet given) or its rejection."""
    verdicts: list[DrawnPlant | dict[str, Any] | None] = []
    designed: list[tuple[int, Candidate, LQIGains]] = []
    for c in candidates:
        if c.plant is None:
            verdicts.append(_rejection(c, "no_bandwidth", str(c.reason)))
            continue
        try:
            gains = check_design(c.plant, checks.max_pole_dt)
        except Rejected as exc:
            verdicts.append(_rejection(c, exc.reason, exc.message))
            continue
        designed.append((len(verdicts), c, gains))
        verdicts.append(None)
    if designed:
        plants = [c.plant for _, c, _ in designed if c.plant is not None]
        dt = plants[0].dt
        times = settling_times(plants, [g for _, _, g in designed], round(checks.duration / dt))
        limit = checks.settle_fraction * checks.duration
        for (slot, c, g), t, p in zip(designed, times, plants, strict=True):
            if t <= limit + 1e-9:
                verdicts[slot] = DrawnPlant(p, c, g, float(t))
            else:
                verdicts[slot] = _rejection(
                    c, "too_slow", f"its LQI unit step settles (2 %) at {t:.4g} s > {limit:g} s"
                )
    return [v for v in verdicts if v is not None]


@dataclass(frozen=True)
class FamilyDraw:
    """The kept plants of a draw, in tag order, and every candidate rejected before the last."""

    family: PlantFamily
    kept: tuple[DrawnPlant, ...]
    rejected: tuple[dict[str, Any], ...]

    @property
    def plants(self) -> list[Plant]:
        """The kept plants, tags ``0 .. count - 1``."""
        return [d.plant for d in self.kept]

    def counts(self) -> dict[str, int]:
        """Candidates tried, kept, and refused per reason (every reason listed)."""
        by = Counter(str(r["reason"]) for r in self.rejected)
        return {"candidates": len(self.kept) + len(self.rejected), "kept": len(self.kept),
                **{r: by.get(r, 0) for r in REASONS}}  # fmt: skip

    def record(self) -> dict[str, Any]:
        """The manifest's ``plant_family`` block: counts, every plant, every rejection."""
        return {
            "name": self.family.name,
            "seed": self.family.seed,
            "counts": self.counts(),
            "plants": {d.plant.name: d.record() for d in self.kept},
            "rejected": list(self.rejected),
        }


def draw_family(
    family: PlantFamily, count: int, checks: FamilyChecks, chunk: int = 256
) -> FamilyDraw:
    """The first ``count`` candidates of ``family`` that pass the checks, and the refused.

    Candidates are checked in chunks, sized by the share kept so far.

    Raises
    ------
    ValueError
        If fewer than ``count`` pass within ``checks.max_tries * count`` candidates, with
        the counts per reason.
    """
    kept: list[DrawnPlant] = []
    rejected: list[dict[str, Any]] = []
    index, limit = 0, checks.max_tries * count
    with threadpool_limits(1, "blas"):  # 5 x 5 matrices: threads only cost
        while len(kept) < count and index < limit:
            rate = len(kept) / index if kept else 1.0
            size = min(max(chunk, math.ceil(1.1 * (count - len(kept)) / rate)), limit - index)
            candidates = [family.candidate(i) for i in range(index, index + size)]
            for verdict in _check_chunk(candidates, checks):
                if len(kept) == count:
                    break
                if isinstance(verdict, DrawnPlant):
                    plant = dataclasses.replace(verdict.plant, tag=len(kept))
                    kept.append(dataclasses.replace(verdict, plant=plant))
                else:
                    rejected.append(verdict)
            index += size
    draw = FamilyDraw(family, tuple(kept), tuple(rejected))
    if len(kept) < count:
        raise ValueError(
            f"plant family '{family.name}': only {len(kept)} of {count} plants pass the checks "
            f"in {index} candidates ({draw.counts()}); widen the family's ranges or relax "
            "families.checks"
        )
    return draw
