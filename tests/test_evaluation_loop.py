"""The evaluation's one loop gives the numbers of a plain loop per scenario and controller."""

from functools import partial

import numpy as np
import pandas as pd
import pytest
import torch

from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.eval_config import SetpointSettings
from generalist_control.evaluation.runner import (
    CONTROLLERS,
    GC_ANTI_WINDUP,
    metric_rows,
    run_suite,
)
from generalist_control.evaluation.setpoint import rest_radii, tail_table
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import (
    AntiWindupLQIController,
    LQIController,
    design_lqi,
)
from generalist_control.simulation.perturbation import Perturbation
from generalist_control.simulation.scenarios import perturbation, references
from generalist_control.simulation.simulate import (
    PerPlantController,
    Run,
    simulate_many,
)
from helpers import lqi_law_policy

NAMES = ("cstr", "two_mass_spring", "two_tank")
#: Two runs per plant at least: the plain loop's BLAS takes the path of several rows too.
SCENARIOS = {
    "random_steps": {"kind": "random_steps", "count": 2, "limit": 5.0, "seed": 1, "duration": 3},
    "staircase": {"kind": "staircase", "count": 2, "limit": 3.0, "x0_fraction": 0.5,
                  "seed": 2, "duration": 4.0},
    "limited": {"kind": "random_steps", "count": 2, "limit": 3.0, "seed": 3, "duration": 2.0,
                "plants": ["two_mass_spring"], "perturbation": {"u_limit": 0.3}},
    "gain_noise": {"kind": "random_steps", "count": 3, "limit": 2.0, "seed": 4, "duration": 2.5,
                   "perturbation": {"actuator_gain": 0.8, "noise_rel": 0.01, "seed": 1}},
}  # fmt: skip


@pytest.fixture(scope="module")
def runtime() -> PolicyRuntime:
    """A real integrating policy: the LQI law plus small random experts (GC is not LQI).

    On ONNX Runtime, the stage's backend, this network's controls for a row do not depend
    on the other rows of its batch. PyTorch's CPU kernels differ with the batch size now and
    then (the last bit of a float32 control), and so do ONNX Runtime's for some networks
    in batches of a few rows (docs/evaluation.md): there the one loop and a loop per
    scenario agree to float32 rounding only.
    """
    pol, meta = lqi_law_policy(NAMES, design_lqi)
    g = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for expert in pol.net.experts:
            expert[-1].weight.normal_(0.0, 0.05, generator=g)
    return PolicyRuntime(pol, meta, backend="onnx")


def _plain(runtime: PolicyRuntime, plants: list) -> pd.DataFrame:
    """The old runner: one simulate_many per scenario and controller."""
    rows = []
    for name, spec in SCENARIOS.items():
        chosen = [p for p in plants if spec.get("plants") is None or p.name in spec["plants"]]
        runs = [Run(p, *references(name, spec, p), perturbation(name, spec, p)) for p in chosen]
        pert = runs[0].perturbation
        ctrls = {
            "GC": RuntimeAdapter(runtime),
            "LQI": PerPlantController(LQIController),
            "LQI-AW": PerPlantController(
                partial(AntiWindupLQIController, limits=pert or Perturbation())
            ),
        }
        if pert is not None and pert.u_limit is not None:
            ctrls[GC_ANTI_WINDUP] = RuntimeAdapter(runtime, pert)
        for ctrl, c in ctrls.items():
            for run, tr in zip(runs, simulate_many(runs, c), strict=True):
                rows += metric_rows(run.plant.name, name, ctrl, spec["kind"], tr)
    columns = ["system", "scenario", "controller", "run", "metric", "value"]
    return pd.DataFrame(rows, columns=columns)


@pytest.mark.parametrize("processes", [1, 2, 3])
def test_the_one_loop_equals_a_loop_per_scenario_exactly(runtime, processes):
    plants = [load_plant(n) for n in NAMES]
    got = run_suite(runtime, plants, SCENARIOS, processes=processes).metrics
    want = _plain(runtime, plants)
    assert set(got.controller) == {*CONTROLLERS, GC_ANTI_WINDUP}
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    assert got.loc[got.metric == "ISE", "value"].notna().all()


def test_the_set_point_holds_in_the_loop_equal_their_own(runtime):
    plants = [load_plant(n) for n in NAMES]
    check = SetpointSettings(reference=1.0, hold=4.0, tail=1.0)
    table = run_suite(runtime, plants, SCENARIOS, setpoint=check, processes=2).setpoint
    assert table is not None and list(table.system) == list(NAMES)
    held = table[["system", "z_end_GC", *(c for c in table if c.startswith("tail_"))]]
    # the linearisation at rest, each share its plants: as the check does it in one process
    alone = rest_radii(runtime, plants, 1.0, held["z_end_GC"]).merge(held, on="system")
    pd.testing.assert_frame_equal(table, alone, check_exact=True)
    # the holds alone have one row per plant: BLAS's path for a single row, the last bits
    holds = run_suite(runtime, plants, {}, setpoint=check, processes=1).setpoint
    pd.testing.assert_frame_equal(held, holds[held.columns], rtol=1e-6)
    # a plain loop of its own with two rows per plant takes the path of several rows: exact
    runs = [Run(p, np.ones((2, 80))) for p in plants]
    adapter = RuntimeAdapter(runtime)
    gc = simulate_many(runs, adapter)
    z_end = runtime.z[::2].copy()
    lqi = simulate_many(runs, PerPlantController(LQIController))
    plain = tail_table(plants, {"GC": gc, "LQI": lqi}, z_end, 1.0, 1.0)
    pd.testing.assert_frame_equal(held, plain, check_exact=True)
