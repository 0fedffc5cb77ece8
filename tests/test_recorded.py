"""Recorded demonstrations (``adapt demos=<file>``): the file format, read back exactly."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from generalist_control.adaptation.new_plant import read_recorded, write_recorded
from generalist_control.data.generation import generate_demos
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import simulate
from helpers import TINY_DATA

FIELDS = ("state", "mask", "ref", "tag", "target")


@pytest.mark.parametrize(("suffix", "controls"), [(".csv", False), (".parquet", True)])
def test_an_lqi_recording_gives_the_data_stage_windows(tmp_path, suffix, controls):
    """A file written from the data stage's LQI simulation reproduces its windows exactly."""
    plant = load_plant("hydraulic_actuator")  # order 3: padding and the integral channel
    demos = generate_demos([plant], TINY_DATA, progress=False)
    path = write_recorded(tmp_path / f"rec{suffix}", plant, demos.x, demos.r, demos.y, demos.u)
    df = pd.read_csv(path) if suffix == ".csv" else pd.read_parquet(path)
    assert list(df.columns) == ["traj", "t", "x0", "x1", "x2", "r", "y", "u"]
    got = read_recorded(path, plant, tag=plant.tag, history=8, horizon=3, controls=controls)
    want = demos.windows(8, 3, True, controls)  # with the previous-control channel or not
    for key in FIELDS:
        np.testing.assert_array_equal(getattr(got.windows, key), getattr(want, key), err_msg=key)
    assert got.trajectories == len(demos.r) and got.samples == demos.r.size


def test_rows_in_any_order_and_trajectories_of_any_length(tmp_path):
    """Shuffled rows, a trajectory cut short: the windows of each trajectory as recorded."""
    plant = load_plant("mass_spring_damper")
    r = np.array([[1.0] * 30, [-2.0] * 30])
    tr = simulate(plant, LQIController(plant), r)
    path = write_recorded(tmp_path / "rec.csv", plant, tr.x, tr.r, tr.y, tr.u)
    df = pd.read_csv(path)
    df = df[(df.traj == 0) | (df.t < 20 * plant.dt - 1e-9)]  # trajectory 1: 20 samples
    df.sample(frac=1.0, random_state=0).to_csv(path, index=False)
    got = read_recorded(path, plant, tag=25, history=8, horizon=3).windows
    assert len(got) == (30 - 2) + (20 - 2)
    assert set(got.tag.tolist()) == {25}
    # the first window of trajectory 0: the first sample repeated, the expert's next controls
    np.testing.assert_allclose(got.target[0], tr.u[0, :3], rtol=1e-6)
    np.testing.assert_allclose(got.state[0, :, : plant.order], np.zeros((8, 2)))
    # its last window ends at sample 27 (the horizon's 3 controls end the trajectory)
    np.testing.assert_allclose(got.state[27, -1, :2], tr.x[0, 27], rtol=1e-6)
    np.testing.assert_allclose(got.target[27], tr.u[0, 27:30], rtol=1e-6)
    z = plant.dt * np.sum(tr.r[0, :27] - tr.y[0, :27])  # the error integral before sample 27
    np.testing.assert_allclose(got.state[27, -1, 4], z, rtol=1e-5)
