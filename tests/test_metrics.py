"""Step metrics against python-control's step_info and closed-form first-order values."""

import control
import numpy as np
import pytest

from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.metrics import step_metrics, tracking_metrics
from generalist_control.simulation.simulate import simulate


def compare_with_step_info(t, y, r_final):
    ref = control.step_info(y, T=t, yfinal=r_final, SettlingTimeThreshold=0.02)
    ours = step_metrics(t, y, np.zeros_like(y), r_final)
    np.testing.assert_allclose(ours["rise_time"], ref["RiseTime"], atol=1e-12)
    np.testing.assert_allclose(ours["settling_time"], ref["SettlingTime"], atol=1e-12)
    np.testing.assert_allclose(ours["overshoot"], ref["Overshoot"], atol=1e-9)


@pytest.mark.parametrize("zeta", [0.2, 0.5, 0.9])
def test_second_order_against_step_info(zeta):
    sys = control.tf([4.0], [1.0, 4.0 * zeta, 4.0])
    t, y = control.step_response(sys, T=np.arange(0, 15, 0.01))
    compare_with_step_info(t, y, 1.0)


@pytest.mark.parametrize(
    ("name", "amp"), [("cstr", 1.0), ("cstr", -7.0), ("two_mass_spring", 3.0)]
)
def test_lqi_responses_against_step_info(name, amp):
    p = load_plant(name)
    tr = simulate(p, LQIController(p), np.full((1, 300), amp))
    compare_with_step_info(tr.t, tr.y[0], amp)


def test_first_order_closed_form():
    tau, dt = 0.5, 1e-3
    t = np.arange(0, 12, dt)
    for amp in (2.0, -2.0):
        y = amp * (1 - np.exp(-t / tau))
        m = step_metrics(t, y, amp * np.ones(5), amp)
        assert m["rise_time"] == pytest.approx(tau * np.log(9), abs=2 * dt)
        assert m["settling_time"] == pytest.approx(tau * np.log(50), abs=2 * dt)
        assert m["overshoot"] == 0.0
        assert m["ISE"] == pytest.approx(amp**2 * tau / 2, rel=1e-4)
        assert m["ITAE"] == pytest.approx(abs(amp) * tau**2, rel=1e-4)
        assert m["u_max"] == pytest.approx(2.0)
        assert m["steady_state_error"] == pytest.approx(abs(amp) * np.exp(-t[-1] / tau))


def test_batched_equals_single_and_undefined_is_nan():
    t = np.linspace(0, 5, 501)
    y = np.stack([1 - np.exp(-t), 0.5 * (1 - np.exp(-t))])  # second never reaches 90% of 1
    m = step_metrics(t, y, np.zeros((2, 3)), np.array([1.0, 1.0]))
    single = step_metrics(t, y[0], np.zeros(3), 1.0)
    assert m["rise_time"][0] == pytest.approx(single["rise_time"])
    assert np.isnan(m["rise_time"][1]) and np.isnan(m["settling_time"][1])


def test_tracking_metrics_on_sine():
    t = np.linspace(0, 2 * np.pi, 20001)
    tm = tracking_metrics(t, np.zeros_like(t), np.sin(t))
    assert tm["ISE"] == pytest.approx(np.pi, rel=1e-6)
    assert tm["RMSE"] == pytest.approx(np.sqrt(0.5), rel=1e-3)
