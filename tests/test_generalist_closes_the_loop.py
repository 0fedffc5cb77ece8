"""A short training of the default recipe on two plants closes the loop (issue 11).

A small, fast version of the quality bar: the learned generalist (no per-plant head, nothing
started from the experts' gains), trained on two plants' demonstrations with the data's
families and DAgger, tracks a step, a staircase and references from random initial states
it was not trained on, with no divergence and errors near LQI's.
"""

from __future__ import annotations

import numpy as np
import pytest

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.runner import evaluate
from generalist_control.evaluation.summary import summarise
from generalist_control.generate import run as generate
from generalist_control.plants.catalog import load_plant
from helpers import compose_cfg, tiny_train_overrides, train

PLANTS = ("cstr", "hydraulic_actuator")
DATA = (
    "systems=paper",
    f"systems.include=[{','.join(PLANTS)}]",
    "data.duration=6.0",
    "data.amplitudes.segments=[{start: 1.0, stop: 4.0, step: 1.0}]",
    "data.families.staircase.count=4",
    "data.families.sines.count=4",
    "data.families.sweeps.enabled=false",
    "data.families.ramps.count=2",
    "data.families.hold.count=4",
)
TRAIN = (
    "systems=paper",
    f"systems.include=[{','.join(PLANTS)}]",
    "logger.log_model=false",
    "closed_loop.systems=[]",
    "closed_loop_val.duration=4.0",
    "loader.batch_size=128",
    "trainer.max_epochs=24",
    "dagger.start_epoch=4",
    "dagger.every=4",
    "dagger.rounds=4",
    "dagger.sampler.rollouts=4",
    "dagger.sampler.duration=6.0",
    "dagger.sampler.families=1",
)
SCENARIOS = {
    "step": {"kind": "step", "amplitude": 1.0, "duration": 10.0},
    "staircase": {
        "kind": "staircase",
        "count": 2,
        "levels": 3,
        "limit": 3.0,
        "seed": 7,
        "duration": 12.0,
    },  # fmt: skip
    "random_initial": {
        "kind": "hold",
        "count": 3,
        "limit": 1.0,
        "x0_scale": 0.5,
        "seed": 7,
        "duration": 10.0,
    },  # fmt: skip
}


@pytest.mark.slow
def test_a_short_training_of_the_default_recipe_closes_the_loop(tmp_path):
    data = tmp_path / "demos"
    generate(compose_cfg(*DATA, f"paths.data_dir={data}"))
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = compose_cfg(*tiny_train_overrides(data, tmp_path / "run", uri), *TRAIN)
    _, objects = train(cfg)
    runtime = PolicyRuntime(objects["policy"], objects["datamodule"].meta())
    df, _ = evaluate(runtime, [load_plant(p) for p in PLANTS], SCENARIOS)
    summary = summarise(df)
    assert summary["diverged"]["GC"] == {}
    step = summary["ratios"]["step"]
    assert step["worst_ISE_ratio"] < 1.3, step
    assert step["worst_relative_ess_GC"] < 0.05, step
    for scen in ("staircase", "random_initial"):
        assert summary["tracking"][scen]["worst_RMSE_ratio"] < 1.5, summary["tracking"]
    assert np.isfinite(df.value[df.metric == "RMSE"]).all()
