"""The evaluation's figures: a grid where a scenario has many plants, two drawing shares."""

from __future__ import annotations

from functools import partial

import numpy as np

from generalist_control.evaluation.forked_shares import fork_map
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


def test_figures_drawn_in_two_shares_are_the_figures_drawn_in_one(tmp_path):
    here = plot_all(_trajs(), tmp_path / "here")
    shares = fork_map(partial(plot_all, _trajs(), tmp_path / "shared"), [(0, 2), (1, 2)])
    assert sorted(p.name for s in shares for p in s) == sorted(p.name for p in here)
    for path in here:  # the same files, byte for byte
        assert (tmp_path / "shared" / path.name).read_bytes() == path.read_bytes(), path.name
    names = {p.name for p in here}
    assert "plant0_step_sine.png" in names and "plant0_limits.png" in names
    assert "family.png" in names and "plant0_family.png" not in names  # many plants: one grid
