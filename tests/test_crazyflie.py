"""The Crazyflie stand-in: reduces to the linear design model, and its mismatches are felt."""

import numpy as np
import pytest

from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.crazyflie import CrazyflieParams, fly_many
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import simulate

IDEAL = CrazyflieParams(
    mass=0.027,
    drag_quadratic=0.0,
    motor_tau=2e-3,
    thrust_min=-1e3,
    thrust_max=1e3,
    noise_altitude=0.0,
    noise_velocity=0.0,
    substeps=40,
)


def test_ideal_stand_in_reproduces_the_linear_closed_loop():
    p = load_plant("crazyflie_altitude")
    assert p.A[1, 1] == pytest.approx(-IDEAL.drag_linear / IDEAL.mass, rel=1e-6)
    linear = simulate(p, LQIController(p), np.ones((1, 160)))
    flown = fly_many([LQIController(p)], np.ones((1, 800)), params=IDEAL)[0]
    np.testing.assert_allclose(flown.y[0, ::5], linear.y[0], atol=5e-3)


def test_mismatch_limits_and_noise_are_felt_but_tracked():
    p = load_plant("crazyflie_altitude")
    tr = fly_many([LQIController(p)], np.full((2, 2000), 1.0), seed=1)[0]
    assert not tr.diverged.any()
    assert np.all(tr.u + 0.027 * 9.81 >= -1e-9) and np.all(tr.u + 0.027 * 9.81 <= 0.58 + 1e-9)
    assert np.abs(tr.y[:, -200:].mean(axis=1) - 1.0).max() < 0.01  # integral action: no offset
    assert not np.allclose(tr.y[0], tr.y[1])  # different noise per run
    again = fly_many([LQIController(p)], np.full((2, 2000), 1.0), seed=1)[0]
    np.testing.assert_array_equal(tr.y, again.y)


def test_control_period_must_be_a_multiple_of_the_loop():
    with pytest.raises(ValueError, match="not a multiple of the loop period"):
        fly_many(
            [LQIController(load_plant("crazyflie_altitude"))], np.ones((1, 10)), control_dt=0.015
        )
