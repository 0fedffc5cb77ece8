"""Closed-loop evaluation of a trained policy against LQI on every scenario.

Every scenario of ``conf/evaluation`` runs three controllers on each plant it applies to:
the learned Generalist Controller (GC), the LQI expert, and LQI with anti-windup
(LQI-AW, conditional integration against the scenario's actuator limits). A policy that
integrates the tracking error (the ``integral`` channel) winds up like LQI, so in scenarios with
actuator limits it also runs as GC-AW: the same policy, its runtime told the limits that
LQI-AW knows (:meth:`~generalist_control.deploy.runtime.PolicyRuntime.set_actuator_limits`).
All plants of a scenario are simulated in lockstep so the policy is called once per sample
for all of them. A run that diverges is reported as diverged (metric ``diverged`` = 1,
other metrics NaN), never as a huge number in an average.

The ``evaluate`` stage (:mod:`generalist_control.evaluate`) writes the results with
:mod:`generalist_control.evaluation.writer`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from generalist_control.deploy.adapter import RuntimeAdapter, SinglePlantAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.plants.plant import Plant
from generalist_control.simulation.crazyflie import fly
from generalist_control.simulation.lqi import AntiWindupLQIController, LQIController
from generalist_control.simulation.metrics import step_metrics, tracking_metrics
from generalist_control.simulation.scenarios import perturbation, references
from generalist_control.simulation.simulate import (
    BatchController,
    Controller,
    PerPlantController,
    Perturbation,
    Run,
    Trajectory,
    simulate_many,
)

__all__ = ["CONTROLLERS", "GC_ANTI_WINDUP", "STEP_KINDS", "evaluate", "metric_rows"]

CONTROLLERS = ("GC", "LQI", "LQI-AW")
#: Run as well where a scenario limits the actuator and the policy integrates.
GC_ANTI_WINDUP = "GC-AW"
STEP_KINDS = ("step", "random_steps")

log = logging.getLogger(__name__)


def _controller(name: str, runtime: PolicyRuntime, pert: Perturbation | None) -> BatchController:
    if name == "GC":
        return RuntimeAdapter(runtime)
    if name == GC_ANTI_WINDUP:
        return RuntimeAdapter(runtime, pert)
    if name == "LQI":
        return PerPlantController(LQIController)
    limits = pert or Perturbation()
    return PerPlantController(lambda p: AntiWindupLQIController(p, limits))


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
    """The sim-to-real stand-in (:mod:`~generalist_control.simulation.crazyflie`): metric rows."""
    steps = int(round(float(spec.get("duration", 15.0)) * 100))
    r = np.full((int(spec.get("runs", 4)), steps), float(spec.get("amplitude", 1.0)))
    ctrls: dict[str, Controller] = {
        "GC": SinglePlantAdapter(runtime, plant.name),
        "LQI": LQIController(plant),
        "LQI-AW": LQIController(plant),  # no known limits to wind up against here
    }
    trajs["crazyflie_sim2real"] = {}
    rows = []
    for ctrl, c in ctrls.items():
        tr = fly(c, r, control_dt=plant.dt, seed=int(spec.get("seed", 0)))
        trajs["crazyflie_sim2real"][ctrl] = {plant.name: tr}
        rows += metric_rows(plant.name, "crazyflie_sim2real", ctrl, "step", tr)
    return rows


def _scenario(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    name: str,
    spec: Mapping[str, Any],
    trajs: dict[str, dict[str, Trajectory]],
) -> list[tuple[str, str, str, int, str, float]]:
    """Every controller on one scenario's runs; fills ``trajs[controller][system]``."""
    runs = [Run(p, *references(name, spec, p), perturbation(name, spec, p)) for p in plants]
    pert = runs[0].perturbation  # actuator limits are the same for every plant
    limited = pert is not None and (pert.u_limit is not None or pert.rate_limit is not None)
    extra = (GC_ANTI_WINDUP,) if limited and runtime.integral else ()
    rows = []
    for ctrl in (*CONTROLLERS, *extra):
        results = simulate_many(runs, _controller(ctrl, runtime, pert))
        trajs[ctrl] = {p.name: tr for p, tr in zip(plants, results, strict=True)}
        for p, tr in zip(plants, results, strict=True):
            rows += metric_rows(p.name, name, ctrl, spec["kind"], tr)
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


def evaluate(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    scenarios: Mapping[str, Mapping[str, Any]],
    crazyflie: Mapping[str, Any] | None = None,
    progress: bool | None = None,
) -> tuple[pd.DataFrame, dict[str, dict[str, dict[str, Trajectory]]]]:
    """Run every scenario for every controller; return long-form metrics and trajectories.

    Progress: a bar over the scenarios (``progress``; by default only on a terminal) and
    one log line (INFO) per scenario with its counts and time.

    Returns
    -------
    metrics : DataFrame
        Columns ``system, scenario, controller, run, metric, value``.
    trajectories : dict
        ``trajectories[scenario][controller][system]``.
    """
    missing = [p.name for p in plants if p.name not in runtime.tags]
    if missing:
        raise KeyError(
            f"the policy was not trained on {', '.join(missing)}; it knows "
            f"{', '.join(runtime.systems)}. Evaluate a set it was trained on (systems=...)"
        )
    rows: list[tuple] = []
    trajs: dict[str, dict[str, dict[str, Trajectory]]] = {}
    todo = _plants_per_scenario(plants, scenarios)
    bar = tqdm(
        todo.items(),
        desc="evaluate",
        unit="scenario",
        disable=None if progress is None else not progress,
    )
    for i, (name, chosen) in enumerate(bar, 1):
        bar.set_postfix_str(name)
        start, trajs[name] = time.perf_counter(), {}
        rows += _scenario(runtime, chosen, name, scenarios[name], trajs[name])
        log.info(
            "scenario %d/%d %s: %d plants, %d controllers, %.1f s",
            i,
            len(todo),
            name,
            len(chosen),
            len(trajs[name]),
            time.perf_counter() - start,
        )
    if crazyflie and any(p.name == "crazyflie_altitude" for p in plants):
        plant = next(p for p in plants if p.name == "crazyflie_altitude")
        rows += _crazyflie(runtime, plant, crazyflie, trajs)
        log.info("crazyflie_sim2real: %d controllers", len(trajs["crazyflie_sim2real"]))
    df = pd.DataFrame(rows, columns=["system", "scenario", "controller", "run", "metric", "value"])
    return df, trajs
