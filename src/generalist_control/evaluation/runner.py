"""Closed-loop evaluation of a trained policy against LQI on every scenario.

Every scenario of ``conf/evaluation`` runs three controllers on each plant it applies to:
the learned Generalist Controller (GC), the LQI expert, and LQI with anti-windup
(LQI-AW, conditional integration against the scenario's actuator limits). A policy that
integrates the tracking error (the ``integral`` channel) winds up like LQI, so in scenarios with
actuator limits it also runs as GC-AW: the same policy, its runtime told the limits that
LQI-AW knows (:meth:`~generalist_control.deploy.runtime.PolicyRuntime.set_actuator_limits`).
Every scenario, plant and controller runs in one sampled loop
(:func:`~generalist_control.simulation.stacked.simulate_stacked`), so the policy is called once
per sample for all of them, and the plants are advanced once per sample for all their runs;
each run's numbers are those of a loop of its own (docs/evaluation.md). A run that diverges
is reported as diverged (metric ``diverged`` = 1, other metrics NaN), never as a huge number
in an average.

The ``evaluate`` stage (:mod:`generalist_control.evaluate`) writes the results with
:mod:`generalist_control.evaluation.writer`.
"""

from __future__ import annotations

import copy
import logging
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from generalist_control.deploy.adapter import SinglePlantAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.live import FinishingAdapter
from generalist_control.evaluation.setpoint import hold_runs, tail_table
from generalist_control.plants.plant import Plant
from generalist_control.simulation.crazyflie import fly_many
from generalist_control.simulation.lqi import AntiWindupLQIController, LQIController
from generalist_control.simulation.metrics import step_metrics, tracking_metrics
from generalist_control.simulation.references import state_envelopes
from generalist_control.simulation.scenarios import envelope_amplitudes, perturbation, references
from generalist_control.simulation.simulate import (
    Controller,
    PerPlantController,
    Perturbation,
    Run,
    Trajectory,
)
from generalist_control.simulation.stacked import Segment, controller_rows, simulate_stacked

__all__ = [
    "CONTROLLERS",
    "GC_ANTI_WINDUP",
    "STEP_KINDS",
    "COLUMNS",
    "Evaluation",
    "crazyflie_flight",
    "evaluate",
    "metric_rows",
    "run_suite",
]

CONTROLLERS = ("GC", "LQI", "LQI-AW")
#: Run as well where a scenario limits the actuator and the policy integrates.
GC_ANTI_WINDUP = "GC-AW"
STEP_KINDS = ("step", "random_steps")
#: The long form of the metrics.
COLUMNS = ["system", "scenario", "controller", "run", "metric", "value"]

log = logging.getLogger(__name__)


def metric_rows(
    system: str, scenario: str, controller: str, kind: str, tr: Trajectory
) -> list[tuple[str, str, str, int, str, float]]:
    """Long-form rows ``(system, scenario, controller, run, metric, value)`` of a batch.

    Step metrics for step-like ``kind`` (else tracking metrics); a diverged run has
    ``diverged = 1`` and NaN for every other metric.
    """
    if kind in STEP_KINDS:
        m = step_metrics(tr.t[:-1], tr.y[:, :-1], tr.u, tr.r)
    else:
        m = tracking_metrics(tr.t[:-1], tr.y[:, :-1], tr.r)
    out = []
    for i in range(tr.r.shape[0]):
        bad = bool(tr.diverged[i])
        out.append((system, scenario, controller, i, "diverged", float(bad)))
        for key, values in m.items():
            out.append((system, scenario, controller, i, key, np.nan if bad else float(values[i])))
    return out


def _crazyflie(
    runtime: PolicyRuntime,
    plant: Plant,
    spec: Mapping[str, Any],
    trajs: dict[str, dict[str, dict[str, Trajectory]]],
) -> list[tuple[str, str, str, int, str, float]]:
    """The sim-to-real stand-in (:mod:`~generalist_control.simulation.crazyflie`): metric rows.

    GC and LQI fly in one loop on the same noise; LQI-AW knows no limits here, so it is LQI
    (the same law, the same trajectory).
    """
    steps = int(round(float(spec.get("duration", 15.0)) * 100))
    r = np.full((int(spec.get("runs", 4)), steps), float(spec.get("amplitude", 1.0)))
    ctrls: list[Controller] = [SinglePlantAdapter(runtime, plant.name), LQIController(plant)]
    gc, lqi = fly_many(ctrls, r, control_dt=plant.dt, seed=int(spec.get("seed", 0)))
    flown = {"GC": gc, "LQI": lqi, "LQI-AW": lqi}
    trajs["crazyflie_sim2real"] = {c: {plant.name: tr} for c, tr in flown.items()}
    rows = []
    for ctrl, tr in flown.items():
        rows += metric_rows(plant.name, "crazyflie_sim2real", ctrl, "step", tr)
    return rows


def _plants_per_scenario(
    plants: Sequence[Plant], scenarios: Mapping[str, Mapping[str, Any]]
) -> dict[str, list[Plant]]:
    """The plants each scenario runs on (its ``plants``, else all); none: left out."""
    todo = {
        n: [p for p in plants if s.get("plants") is None or p.name in s["plants"]]
        for n, s in scenarios.items()
    }
    return {n: chosen for n, chosen in todo.items() if chosen}


def _run(name: str, spec: Mapping[str, Any], plant: Plant) -> Run:
    return Run(plant, *references(name, spec, plant), perturbation(name, spec, plant))


def _limits(runs: Sequence[Run]) -> Perturbation | None:
    """The scenario's perturbation if it limits the actuator (the same for every plant)."""
    pert = runs[0].perturbation
    limited = pert is not None and (pert.u_limit is not None or pert.rate_limit is not None)
    return pert if limited else None


#: Where a run's trajectory comes back: (segment, run in that segment).
Slot = tuple[int, int]


@dataclass
class _Plan:
    """Every scenario's runs as segments of one loop, and where each result comes back.

    GC is split by plant into ``parts`` segments, each with its own copy of the runtime
    (the same network), stepped in threads side by side; one LQI segment holds every run.
    The set-point holds join both. A scenario that limits the actuator adds an LQI-AW
    segment and, for a policy that integrates the error, a GC-AW segment with its own copy
    of the runtime (the limits are the runtime's). Elsewhere LQI-AW knows no limits and is
    LQI exactly (the same law, the same arithmetic), so LQI's trajectories serve for it.
    """

    segments: list[Segment] = field(default_factory=list)
    #: (scenario, controller) -> per plant of the scenario, its slot
    where: dict[tuple[str, str], list[Slot]] = field(default_factory=dict)
    held: dict[str, list[Slot]] = field(default_factory=dict)
    gc: list[FinishingAdapter] = field(default_factory=list)

    def add(self, segment: int, run: Run) -> Slot:
        """Append ``run`` to a segment; its slot."""
        runs = self.segments[segment].runs
        assert isinstance(runs, list)
        runs.append(run)
        return segment, len(runs) - 1


#: GC's rows are split between runtime copies from this many rows on. Fewer gain nothing
#: from two threads, and a batch of a few rows can meet other kernels than the old loop's
#: batch (ONNX Runtime's results depend on the batch size below about 8 rows for some
#: networks: docs/evaluation.md).
SPLIT_ROWS = 64
#: The share of GC's rows that part 0 takes: it steps in the loop's own thread, which steps
#: every other segment too while the other parts step in theirs.
FIRST_SHARE = 0.4


def _shares(runs: Sequence[Run], parts: int) -> dict[str, int]:
    """Which GC part each plant goes to: contiguous groups of plants by their rows.

    Part 0 takes about :data:`FIRST_SHARE` of the rows (all of them with one part), the
    others share the rest equally.
    """
    rows: dict[str, int] = {}
    for run in runs:
        rows[run.plant.name] = rows.get(run.plant.name, 0) + np.atleast_2d(run.r).shape[0]
    total, seen, out = max(sum(rows.values()), 1), 0, {}
    first = FIRST_SHARE if parts > 1 else 1.0
    for name, n in rows.items():
        share = seen / total  # where the plant's rows start
        later = 1 + int((parts - 1) * (share - first) / (1 - first)) if share >= first else 0
        out[name] = min(parts - 1, later)
        seen += n
    return out


def _plan(
    runtime: PolicyRuntime, todo: Mapping[str, list[Run]], held: list[Run], parts: int
) -> _Plan:
    plan = _Plan()
    every = [run for runs in todo.values() for run in runs] + held
    if sum(np.atleast_2d(run.r).shape[0] for run in every) < SPLIT_ROWS:
        parts = 1
    parts = max(1, min(parts, len({run.plant.name for run in every})))  # a plant per part at least
    share = _shares(every, parts)
    for i in range(parts):  # part 0 drives the runtime itself, the others copies of it
        plan.gc.append(FinishingAdapter(runtime if i == 0 else copy.copy(runtime)))
        plan.segments.append(Segment(plan.gc[i], [], concurrent=i > 0))
    lqi = len(plan.segments)
    plan.segments.append(Segment(PerPlantController(LQIController), []))
    for name, runs in todo.items():
        plan.where[name, "GC"] = [plan.add(share[r.plant.name], r) for r in runs]
        plan.where[name, "LQI"] = plan.where[name, "LQI-AW"] = [plan.add(lqi, r) for r in runs]
        limits = _limits(runs)
        if limits is None:
            continue
        aw = PerPlantController(partial(AntiWindupLQIController, limits=limits))
        plan.segments.append(Segment(aw, []))
        plan.where[name, "LQI-AW"] = [plan.add(len(plan.segments) - 1, r) for r in runs]
        if runtime.integral:
            twin = copy.copy(runtime)  # its own rows and limits, the same network
            plan.segments.append(Segment(FinishingAdapter(twin, limits), []))
            plan.where[name, GC_ANTI_WINDUP] = [plan.add(len(plan.segments) - 1, r) for r in runs]
    plan.held = {"GC": [plan.add(share[r.plant.name], r) for r in held],
                 "LQI": [plan.add(lqi, r) for r in held]}  # fmt: skip
    return plan


def _held(
    plan: _Plan,
    results: list[list[Trajectory]],
    plants: Sequence[Plant],
    hold: tuple[float, float, float],
) -> pd.DataFrame:
    """The set-point holds' table (:func:`~generalist_control.evaluation.setpoint.tail_table`)."""
    local = controller_rows(plan.segments)
    rows = [(plan.gc[s], local[s][i].start) for s, i in plan.held["GC"]]
    refused = any(row in gc.refused for gc, row in rows)
    z = np.nan if refused else np.array([gc.z_end[row] for gc, row in rows])
    trajs = {c: [results[s][i] for s, i in plan.held[c]] for c in ("GC", "LQI")}
    return tail_table(plants, trajs, z, hold[0], hold[2])


class _Progress:
    """A bar over the scenarios and one log line per scenario as its runs end."""

    def __init__(self, plan: _Plan, todo: Mapping[str, list[Run]], progress: bool | None) -> None:
        self.plan, self.todo, self.start = plan, todo, time.perf_counter()
        disable = None if progress is None else not progress
        self.bar = tqdm(total=len(todo), desc="evaluate", unit="scenario", disable=disable)

    def __call__(self, k: int, done: list[Slot]) -> None:
        ended = [n for n in self.todo if self.plan.where[n, "LQI"][0] in done]
        for name in ended:
            i = list(self.todo).index(name) + 1
            controllers = sum((name, c) in self.plan.where for c in (*CONTROLLERS, GC_ANTI_WINDUP))
            self.bar.set_postfix_str(name)
            self.bar.update(1)
            log.info(
                "scenario %d/%d %s: %d plants, %d controllers, %d samples, done after %.1f s",
                i, len(self.todo), name, len(self.todo[name]), controllers, k,
                time.perf_counter() - self.start,
            )  # fmt: skip


@dataclass(frozen=True)
class Evaluation:
    """What :func:`run_suite` returns.

    Attributes
    ----------
    metrics : DataFrame
        Columns ``system, scenario, controller, run, metric, value``.
    trajectories : dict
        ``trajectories[scenario][controller][system]``.
    held : DataFrame or None
        The set-point holds' table (:func:`~generalist_control.evaluation.setpoint.hold_tail`)
        when ``hold`` was given.
    """

    metrics: pd.DataFrame
    trajectories: dict[str, dict[str, dict[str, Trajectory]]]
    held: pd.DataFrame | None = None

    def joined(self, other: Evaluation) -> Evaluation:
        """The scenarios of both, these first (``other.held`` is ignored)."""
        metrics = pd.concat([self.metrics, other.metrics], ignore_index=True)
        return Evaluation(metrics, {**self.trajectories, **other.trajectories}, self.held)


def _check_known(runtime: PolicyRuntime, plants: Sequence[Plant]) -> None:
    missing = [p.name for p in plants if p.name not in runtime.tags]
    if missing:
        raise KeyError(
            f"the policy was not trained on {', '.join(missing)}; it knows "
            f"{', '.join(runtime.systems)}. Evaluate a set it was trained on (systems=...)"
        )


def run_suite(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    scenarios: Mapping[str, Mapping[str, Any]],
    crazyflie: Mapping[str, Any] | None = None,
    hold: tuple[float, float, float] | None = None,
    progress: bool | None = None,
    threads: int | None = None,
) -> Evaluation:
    """Every scenario under every controller in one loop (and the set-point holds).

    ``hold``: ``(reference, hold, tail)`` of the set-point check's long steps
    (:func:`~generalist_control.evaluation.setpoint.setpoint_settings`), run in the same loop.
    ``threads``: how many runtime copies share GC's rows, stepped side by side (at most 2;
    default: 2 where there are 2 cores); the numbers do not depend on it.
    Progress: a bar over the scenarios (``progress``; by default only on a terminal) and
    one log line (INFO) per scenario as its runs end.
    """
    _check_known(runtime, plants)
    chosen = _plants_per_scenario(plants, scenarios)
    # the envelopes of random initial states and relative noise, all in one loop
    state_envelopes([(p, a) for n, ps in chosen.items() for p in ps
                     for a in envelope_amplitudes(scenarios[n])])  # fmt: skip
    todo = {name: [_run(name, scenarios[name], p) for p in ps] for name, ps in chosen.items()}
    held = hold_runs(plants, hold[0], hold[1]) if hold else []
    parts = max(1, min(int(threads or os.cpu_count() or 1), 2))
    plan = _plan(runtime, todo, held, parts)
    bar = _Progress(plan, todo, progress)
    results = simulate_stacked(plan.segments, on_end=bar)
    bar.bar.close()
    rows: list[tuple] = []
    trajs: dict[str, dict[str, dict[str, Trajectory]]] = {}
    for name, runs in todo.items():
        trajs[name] = {}
        for ctrl in (c for c in (*CONTROLLERS, GC_ANTI_WINDUP) if (name, c) in plan.where):
            got = [results[s][i] for s, i in plan.where[name, ctrl]]
            trajs[name][ctrl] = {run.plant.name: tr for run, tr in zip(runs, got, strict=True)}
            for run, tr in zip(runs, got, strict=True):
                rows += metric_rows(run.plant.name, name, ctrl, scenarios[name]["kind"], tr)
    ev = Evaluation(pd.DataFrame(rows, columns=COLUMNS), trajs,
                    _held(plan, results, plants, hold) if hold else None)  # fmt: skip
    flight = crazyflie_flight(runtime, plants, crazyflie)
    return ev if flight is None else ev.joined(flight)


def crazyflie_flight(
    runtime: PolicyRuntime, plants: Sequence[Plant], spec: Mapping[str, Any] | None
) -> Evaluation | None:
    """The sim-to-real stand-in's scenario ``crazyflie_sim2real`` (None: off, or no plant)."""
    plant = next((p for p in plants if p.name == "crazyflie_altitude"), None)
    if not spec or plant is None:
        return None
    trajs: dict[str, dict[str, dict[str, Trajectory]]] = {}
    rows = _crazyflie(runtime, plant, spec, trajs)
    log.info("crazyflie_sim2real: %d controllers", len(trajs["crazyflie_sim2real"]))
    return Evaluation(pd.DataFrame(rows, columns=COLUMNS), trajs)


def evaluate(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    scenarios: Mapping[str, Mapping[str, Any]],
    crazyflie: Mapping[str, Any] | None = None,
    progress: bool | None = None,
) -> tuple[pd.DataFrame, dict[str, dict[str, dict[str, Trajectory]]]]:
    """Run every scenario for every controller; return long-form metrics and trajectories.

    :func:`run_suite` without the set-point holds.

    Returns
    -------
    metrics : DataFrame
        Columns ``system, scenario, controller, run, metric, value``.
    trajectories : dict
        ``trajectories[scenario][controller][system]``.
    """
    ev = run_suite(runtime, plants, scenarios, crazyflie, progress=progress)
    return ev.metrics, ev.trajectories
