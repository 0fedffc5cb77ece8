"""The evaluation's loop of one share of the plants: its segments, and its progress."""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from tqdm.auto import tqdm

from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.simulation.lqi import AntiWindupLQIController, LQIController
from generalist_control.simulation.perturbation import Perturbation
from generalist_control.simulation.simulate import PerPlantController, Run, Segment

__all__ = ["GC_ANTI_WINDUP", "Key", "Plan", "Progress", "Slot", "limits", "plan"]

#: Run as well where a scenario limits the actuator and the policy integrates.
GC_ANTI_WINDUP = "GC-AW"

log = logging.getLogger(__name__)


def limits(runs: Sequence[Run]) -> Perturbation | None:
    """The scenario's perturbation if it limits the actuator (the same for every plant)."""
    pert = runs[0].perturbation
    limited = pert is not None and (pert.u_limit is not None or pert.rate_limit is not None)
    return pert if limited else None


#: Where a run's trajectory comes back: (segment, run in that segment).
Slot = tuple[int, int]
#: A run's results by (scenario, controller, plant).
Key = tuple[str, str, str]


@dataclass
class Plan:
    """Every scenario's runs as segments of one loop, and where each result comes back.

    One GC and one LQI segment hold every run and the set-point holds. A scenario that limits
    the actuator adds LQI-AW and (an integrating policy) GC-AW segments; elsewhere LQI-AW is
    LQI exactly, so LQI's trajectories serve for it.
    """

    segments: list[Segment] = field(default_factory=list)
    #: (scenario, controller) -> per plant of the scenario, its slot
    where: dict[tuple[str, str], list[Slot]] = field(default_factory=dict)
    held: dict[str, list[Slot]] = field(default_factory=dict)

    def add(self, segment: int, run: Run) -> Slot:
        """Append ``run`` to a segment; its slot."""
        runs = self.segments[segment].runs
        assert isinstance(runs, list)
        runs.append(run)
        return segment, len(runs) - 1


def plan(runtime: PolicyRuntime, todo: Mapping[str, list[Run]], held: list[Run]) -> Plan:
    """The segments of ``todo``'s runs and the set-point holds ``held`` (see :class:`Plan`)."""
    out = Plan()
    gc, lqi = RuntimeAdapter(runtime), 1
    out.segments += [Segment(gc, []), Segment(PerPlantController(LQIController), [])]
    for name, runs in todo.items():
        out.where[name, "GC"] = [out.add(0, r) for r in runs]
        out.where[name, "LQI"] = out.where[name, "LQI-AW"] = [out.add(lqi, r) for r in runs]
        limited = limits(runs)
        if limited is None:
            continue
        aw = PerPlantController(partial(AntiWindupLQIController, limits=limited))
        out.segments.append(Segment(aw, []))
        out.where[name, "LQI-AW"] = [out.add(len(out.segments) - 1, r) for r in runs]
        if runtime.integral:
            twin = copy.copy(runtime)  # its own rows and limits, the same network
            out.segments.append(Segment(RuntimeAdapter(twin, limited), []))
            out.where[name, GC_ANTI_WINDUP] = [out.add(len(out.segments) - 1, r) for r in runs]
    out.held = {c: [out.add(s, r) for r in held] for c, s in (("GC", 0), ("LQI", lqi))}
    return out


class Progress:
    """A bar over the scenarios and a log line for each as this process's loop passes its end."""

    def __init__(
        self, todo: Mapping[str, list[Run]], integral: bool, progress: bool | None
    ) -> None:
        self.todo, self.integral, self.start = todo, integral, time.perf_counter()
        self.length = {n: max(np.atleast_2d(r.r).shape[1] for r in runs)
                       for n, runs in todo.items()}  # fmt: skip
        self.told: set[str] = set()
        disable = None if progress is None else not progress
        self.bar = tqdm(total=len(todo), desc="evaluate", unit="scenario", disable=disable)

    def __call__(self, k: int, done: Sequence[Slot] = ()) -> None:
        """The scenarios whose last sample is before sample ``k`` are done."""
        ended = [n for n in self.todo if n not in self.told and self.length[n] <= k]
        for name in ended:
            i = list(self.todo).index(name) + 1
            aw = self.integral and limits(self.todo[name]) is not None  # GC-AW runs too
            self.told.add(name)
            self.bar.set_postfix_str(name)
            self.bar.update(1)
            log.info(
                "scenario %d/%d %s: %d plants, %d controllers, %d samples, done after %.1f s",
                i, len(self.todo), name, len(self.todo[name]), 3 + aw,
                self.length[name], time.perf_counter() - self.start,
            )  # fmt: skip

    def close(self) -> None:
        """Every scenario is done: the ones not told yet, then the bar closed."""
        self(max(self.length.values(), default=0))
        self.bar.close()
