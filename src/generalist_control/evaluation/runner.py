"""Closed-loop evaluation of a trained policy against LQI on every scenario.

GC, LQI and LQI with anti-windup (and GC-AW where the actuator is limited and the policy
integrates) run in one sampled loop per share of the plants, two shares side by side
(docs/evaluation.md); a diverged run is reported as ``diverged`` = 1, its metrics NaN.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.deploy.adapter import RuntimeAdapter, SinglePlantAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.eval_config import CrazyflieSettings, SetpointSettings
from generalist_control.evaluation.forked_shares import balanced, fork_map
from generalist_control.evaluation.loop_layout import GC_ANTI_WINDUP, Key, Progress, plan
from generalist_control.evaluation.setpoint import hold_runs, rest_radii, tail_table
from generalist_control.plants.definition import Plant
from generalist_control.simulation.crazyflie import fly_many
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.metrics import step_metrics, tracking_metrics
from generalist_control.simulation.references import state_envelopes
from generalist_control.simulation.scenarios import (
    envelope_amplitudes,
    perturbation,
    references,
    runs_on,
)
from generalist_control.simulation.simulate import (
    Controller,
    Run,
    Trajectory,
    controller_rows,
    simulate_stacked,
)

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


def _flight_shape(spec: CrazyflieSettings) -> tuple[int, int]:
    """The Crazyflie stand-in's references: (runs, samples at its 100 Hz)."""
    return spec.runs, int(round(spec.duration * 100))


def _plants_per_scenario(
    plants: Sequence[Plant], scenarios: Mapping[str, Mapping[str, Any]]
) -> dict[str, list[Plant]]:
    """The plants each scenario runs on (its ``plants``, else all); none: left out."""
    todo = {n: [p for p in plants if runs_on(s, p.name)] for n, s in scenarios.items()}
    return {n: chosen for n, chosen in todo.items() if chosen}


def _run(name: str, spec: Mapping[str, Any], plant: Plant) -> Run:
    return Run(plant, *references(name, spec, plant), perturbation(name, spec, plant))


@dataclass(frozen=True)
class Evaluation:
    """Metrics (:data:`COLUMNS`), ``trajectories[scenario][controller][system]``, set point."""

    metrics: pd.DataFrame
    trajectories: dict[str, dict[str, dict[str, Trajectory]]]
    setpoint: pd.DataFrame | None = None


@dataclass
class _Share:
    """What one share of the plants gives back (pickled from a forked child)."""

    rows: dict[Key, list[tuple]]
    trajs: dict[Key, Trajectory]
    setpoint: pd.DataFrame | None = None
    flight: Evaluation | None = None


def _check_known(runtime: PolicyRuntime, plants: Sequence[Plant]) -> None:
    missing = [p.name for p in plants if p.name not in runtime.tags]
    if missing:
        raise KeyError(
            f"the policy was not trained on {', '.join(missing)}; it knows "
            f"{', '.join(runtime.systems)}. Evaluate a set it was trained on (systems=...)"
        )


@dataclass(frozen=True)
class _Suite:
    """Everything a share needs: the runs of every plant, the checks asked for."""

    runtime: PolicyRuntime
    scenarios: Mapping[str, Mapping[str, Any]]
    todo: Mapping[str, list[Run]]
    held: list[Run]
    crazyflie: CrazyflieSettings | None
    setpoint: SetpointSettings | None
    bar: Progress

    def share(self, job: tuple[int, list[Plant]]) -> _Share:
        """One loop for the runs of ``plants`` (the bar for share 0, this process's)."""
        index, plants = job
        mine = {id(p) for p in plants}
        todo = {n: [r for r in runs if id(r.plant) in mine] for n, runs in self.todo.items()}
        todo = {n: runs for n, runs in todo.items() if runs}
        held = [r for r in self.held if id(r.plant) in mine]
        layout = plan(self.runtime, todo, held)
        results = simulate_stacked(layout.segments, on_end=self.bar if index == 0 else None)
        out = _Share({}, {})
        for (name, ctrl), slots in layout.where.items():
            kind = self.scenarios[name]["kind"]
            for run, (s, i) in zip(todo[name], slots, strict=True):
                tr = results[s][i]
                out.trajs[name, ctrl, run.plant.name] = tr
                out.rows[name, ctrl, run.plant.name] = metric_rows(
                    run.plant.name, name, ctrl, kind, tr
                )
        if self.setpoint is not None:
            reference, tail = self.setpoint.reference, self.setpoint.tail
            local = controller_rows(layout.segments)
            gc = layout.segments[0].controller
            assert isinstance(gc, RuntimeAdapter)
            z = np.array([gc.z_end[local[s][i].start] for s, i in layout.held["GC"]])
            trajs = {c: [results[s][i] for s, i in layout.held[c]] for c in ("GC", "LQI")}
            held = tail_table(plants, trajs, z, reference, tail)
            out.setpoint = rest_radii(self.runtime, plants, reference, z).merge(held, on="system")
        out.flight = crazyflie_flight(self.runtime, plants, self.crazyflie)
        return out


#: Suites of less work (samples times rows, both controllers) run in one process.
SPLIT_WORK = 50_000
#: Cost of a nonlinear plant's RK4 update per sample, in samples times rows.
_RK4_COST = 50
#: Cost of a Crazyflie stand-in's sample (100 Hz, nonlinear), in samples times rows.
_FLIGHT_COST = 12


def _costs(plants: Sequence[Plant], suite: _Suite) -> list[float]:
    """Each plant's share of the work, roughly (samples times rows; the split's balance)."""
    cost = {id(p): 0.0 for p in plants}
    longest = {id(p): 0 for p in plants}
    for run in [r for runs in suite.todo.values() for r in runs] + suite.held:
        b, n = np.atleast_2d(run.r).shape
        cost[id(run.plant)] += 2.0 * b * n  # GC and LQI
        longest[id(run.plant)] = max(longest[id(run.plant)], n)
    for p in plants:
        if not p.is_linear:
            cost[id(p)] += _RK4_COST * longest[id(p)]
        if suite.crazyflie is not None and p.name == "crazyflie_altitude":
            cost[id(p)] += _FLIGHT_COST * float(np.prod(_flight_shape(suite.crazyflie)))
    return [cost[id(p)] for p in plants]


def _merge(plants: Sequence[Plant], suite: _Suite, shares: Sequence[_Share]) -> Evaluation:
    """The shares' results in the order one loop gives them: scenario, controller, plant."""
    rows_by = {k: v for sh in shares for k, v in sh.rows.items()}
    trajs_by = {k: v for sh in shares for k, v in sh.trajs.items()}
    rows: list[tuple] = []
    trajs: dict[str, dict[str, dict[str, Trajectory]]] = {}
    for name, runs in suite.todo.items():
        trajs[name] = {}
        for ctrl in (*CONTROLLERS, GC_ANTI_WINDUP):
            keys = [(name, ctrl, run.plant.name) for run in runs]
            if keys[0] not in trajs_by:
                continue
            trajs[name][ctrl] = {k[2]: trajs_by[k] for k in keys}
            rows += [row for k in keys for row in rows_by[k]]
    setpoint = None
    if suite.setpoint is not None:  # in the plants' order
        tables = pd.concat([sh.setpoint for sh in shares if sh.setpoint is not None])
        setpoint = tables.set_index("system").loc[[p.name for p in plants]].reset_index()
    ev = Evaluation(pd.DataFrame(rows, columns=COLUMNS), trajs, setpoint)
    for flight in (sh.flight for sh in shares if sh.flight is not None):
        metrics = pd.concat([ev.metrics, flight.metrics], ignore_index=True)
        ev = Evaluation(metrics, {**ev.trajectories, **flight.trajectories}, ev.setpoint)
    return ev


def run_suite(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    scenarios: Mapping[str, Mapping[str, Any]],
    crazyflie: CrazyflieSettings | None = None,
    setpoint: SetpointSettings | None = None,
    progress: bool | None = None,
    processes: int | None = None,
) -> Evaluation:
    """Every scenario under every controller in one loop, the Crazyflie, the set point.

    ``setpoint``: the set-point check (:mod:`~.setpoint`), its holds in the same loop.
    ``processes``: shares of the plants of about equal work, the others in forked children
    (default 2 on 2 cores for a suite of :data:`SPLIT_WORK` or more); each run's numbers do
    not depend on it. ``progress``: a bar (default: on a terminal).

    Raises
    ------
    ValueError
        A set-point check of a policy that does not integrate the tracking error (no
        ``integral`` channel): without it a constant window need not be an equilibrium.
    """
    _check_known(runtime, plants)
    if setpoint is not None and not runtime.integral:
        raise ValueError(
            "the set-point check needs a policy with the integral channel (model.channels; its "
            "equilibrium is the error integral at which its control holds the plant at rest)"
        )
    chosen = _plants_per_scenario(plants, scenarios)
    # the envelopes of random initial states and relative noise, all in one loop
    state_envelopes([(p, a) for n, ps in chosen.items() for p in ps
                     for a in envelope_amplitudes(n, scenarios[n])])  # fmt: skip
    todo = {name: [_run(name, scenarios[name], p) for p in ps] for name, ps in chosen.items()}
    held = hold_runs(plants, setpoint.reference, setpoint.hold) if setpoint else []
    bar = Progress(todo, runtime.integral, progress)
    suite = _Suite(runtime, scenarios, todo, held, crazyflie, setpoint, bar)
    costs = _costs(plants, suite)
    if processes is None:
        processes = 2 if (os.cpu_count() or 1) >= 2 and sum(costs) >= SPLIT_WORK else 1
    groups = balanced(costs, max(1, min(int(processes), len(plants))))
    # the share with the first plant here: its progress is this process's
    jobs = [(i, [plants[j] for j in g]) for i, g in enumerate(groups)]
    try:
        shares = fork_map(suite.share, jobs)
    except BaseException:
        suite.bar.bar.close()
        raise
    suite.bar.close()
    return _merge(plants, suite, shares)


def crazyflie_flight(
    runtime: PolicyRuntime, plants: Sequence[Plant], spec: CrazyflieSettings | None
) -> Evaluation | None:
    """The sim-to-real stand-in's scenario ``crazyflie_sim2real`` (None: off, or no plant).

    GC and LQI fly in one loop on the same noise; LQI-AW knows no limits here: it is LQI.
    """
    plant = next((p for p in plants if p.name == "crazyflie_altitude"), None)
    if spec is None or plant is None:
        return None
    r = np.full(_flight_shape(spec), spec.amplitude)
    ctrls: list[Controller] = [SinglePlantAdapter(runtime, plant.name), LQIController(plant)]
    gc, lqi = fly_many(ctrls, r, control_dt=plant.dt, seed=spec.seed)
    flown = {"GC": gc, "LQI": lqi, "LQI-AW": lqi}
    rows = []
    for c, tr in flown.items():
        rows += metric_rows(plant.name, "crazyflie_sim2real", c, "step", tr)
    log.info("crazyflie_sim2real: %d controllers", len(flown))
    trajs = {"crazyflie_sim2real": {c: {plant.name: tr} for c, tr in flown.items()}}
    return Evaluation(pd.DataFrame(rows, columns=COLUMNS), trajs)


def evaluate(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    scenarios: Mapping[str, Mapping[str, Any]],
    crazyflie: CrazyflieSettings | None = None,
    progress: bool | None = None,
) -> tuple[pd.DataFrame, dict[str, dict[str, dict[str, Trajectory]]]]:
    """:func:`run_suite` without the set-point check: its metrics and trajectories."""
    ev = run_suite(runtime, plants, scenarios, crazyflie, progress=progress)
    return ev.metrics, ev.trajectories
