"""The evaluation's figures: fewer, and drawn in forked processes beside the evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from generalist_control.evaluation.background import FigureJob, figures_beside
from generalist_control.evaluation.plots import PER_PLANT, plot_all
from generalist_control.simulation.simulate import Trajectory


def _tr(seed: int, rows: int = 1, n: int = 40) -> Trajectory:
    rng = np.random.default_rng(seed)
    y = np.cumsum(rng.normal(size=(rows, n + 1)), axis=1)
    return Trajectory(
        t=np.arange(n + 1) * 0.05, x=y[..., None], u=rng.normal(size=(rows, n)),
        r=np.ones((rows, n)), y=y, diverged=np.zeros(rows, bool),
    )  # fmt: skip


def _trajs() -> dict:
    systems = [f"plant{i}" for i in range(PER_PLANT + 2)]
    return {
        "step": {c: {s: _tr(i) for i, s in enumerate(systems)} for c in ("GC", "LQI")},
        "sine": {c: {s: _tr(i + 9) for i, s in enumerate(systems)} for c in ("GC", "LQI")},
        "limits": {c: {"plant0": _tr(3)} for c in ("GC", "GC-AW", "LQI", "LQI-AW")},
        "family": {c: {s: _tr(i, rows=2) for i, s in enumerate(systems)} for c in ("GC", "LQI")},
    }


@pytest.mark.parametrize("forked", [True, False])
def test_figures_drawn_beside_are_the_figures_drawn_here(tmp_path, forked):
    here = sorted(p.name for p in plot_all(_trajs(), tmp_path / "here"))
    trajs = _trajs()
    later = {"limits": trajs.pop("limits")}  # a scenario that ends later (the Crazyflie's)
    job = FigureJob(trajs, forked=forked)
    job.add(later)
    try:
        beside = sorted(p.name for p in job.collect(tmp_path / "beside"))
    finally:
        job.close()
    assert beside == here
    assert "plant0_step_sine.png" in here and "plant0_limits.png" in here
    assert "family.png" in here and "plant0_family.png" not in here  # many plants: one grid
    assert not job.dir.exists()


def test_a_failed_drawing_is_an_error_not_a_missing_figure(tmp_path):
    broken = {"limits": {"GC": {"plant0": None}}}
    with figures_beside(broken) as job, pytest.raises(RuntimeError, match="figures failed"):
        assert job is not None
        job.collect(tmp_path / "plots")
