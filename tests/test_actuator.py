"""DAgger's rollouts through an actuator that is not the model's (dagger.sampler.actuator)."""

from __future__ import annotations

import numpy as np
import pytest

from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import plant_stepper
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.sampler import Actuator, lag_mix, run_rollouts
from generalist_control.training.settings import LabellerSettings
from helpers import config_section


def aggregate(plant, amps, steps, seed=0, actuator=None):
    """A pure-expert round on ``plant`` whose windows carry the previous control."""
    refs = (np.repeat(amps[:, None], steps, axis=1), None)
    rollouts = run_rollouts([plant], [refs], None, 1.0, None, seed, actuator)
    labeller = ExpertLabeller(
        config_section(LabellerSettings, "dagger.labeller"), 8, 3, ["previous_control"]
    )
    return labeller.label(rollouts, {plant.name: np.full(plant.order, np.inf)})


FINE = 20000  # Euler steps per sample of the reference lag


def _fine_lag(tau: float, s0: float, u: float) -> tuple[float, float]:
    """Mean and end over one sample of ``tau ds/dt = u - s`` from ``s0`` (fine Euler)."""
    if tau == 0:
        return u, u
    s, total, h = s0, 0.0, 1.0 / FINE
    for _ in range(FINE):
        total += s + 0.5 * h * (u - s) / tau  # trapezoid within the step
        s += h * (u - s) / tau
    return total / FINE, s


@pytest.mark.parametrize("tau", [0.0, 0.2, 0.6, 1.0, 3.0])
def test_lag_mix_is_a_first_order_lags_mean_and_end_over_a_sample(tau):
    mix, decay = lag_mix(np.array([tau]))
    s0, u = 0.7, -1.3
    mean, end = _fine_lag(tau, s0, u)
    assert u + mix[0] * (s0 - u) == pytest.approx(mean, abs=2e-4)
    assert u + decay[0] * (s0 - u) == pytest.approx(end, abs=2e-4)


def test_the_actuator_delivers_a_lagged_command_plus_its_offset():
    """Per row: time constant in [0, lag], offset in +-offset, the lag's mean plus the offset."""
    lag, off = np.array([1.0, 0.5, 0.0, 2.0]), np.array([0.3, 0.0, 0.2, 1.0])
    act = Actuator(lag, off, np.random.default_rng(3))
    assert np.all((act.tau >= 0) & (act.tau <= lag)) and np.all(np.abs(act.d) <= off)
    assert act.tau[2] == 0 and act.d[1] == 0 and act.tau[0] > 0 and act.d[3] != 0
    cmds = np.random.default_rng(4).normal(size=(12, 4))
    s = np.zeros(4)  # the reference lags, from rest
    for u in cmds:
        got = act(u)
        for i in range(4):
            mean, s[i] = _fine_lag(float(act.tau[i]), float(s[i]), float(u[i]))
            assert got[i] == pytest.approx(mean + act.d[i], abs=5e-4)
    assert np.array_equal(Actuator(np.zeros(2), np.zeros(2), np.random.default_rng(0))(
        np.array([1.5, -2.0])), [1.5, -2.0])  # fmt: skip
    with pytest.raises(ValueError, match="the actuator's lag must be finite and >= 0"):
        Actuator(np.array([-1.0]), np.array([0.0]), np.random.default_rng(0))
    with pytest.raises(ValueError, match="must be \\(rows,\\) alike"):
        Actuator(np.zeros(2), np.zeros(3), np.random.default_rng(0))


def test_rollouts_through_the_actuator_move_the_plant_and_keep_the_command():
    """Pure-expert round on a linear plant, against a hand-built loop through the actuator.

    The plant receives the actuator's output; the windows carry the expert's *command*
    (the previous-control channel) and are labelled by its law at the visited states.
    """
    plant = load_plant("dc_servo")
    steps, seed, spread = 40, 5, {plant.name: (1.0, 0.4)}
    amps = np.array([1.0, -2.0])
    refs = np.repeat(amps[:, None], steps, axis=1)
    w, _ = aggregate(plant, amps, steps, seed, spread)
    act = Actuator(np.full(2, 1.0), np.full(2, 0.4), np.random.default_rng(seed))
    advance, lqi = plant_stepper(plant), LQIController(plant)
    lqi.reset(2)
    x, xs, cmd, zs = np.zeros((2, plant.order)), [], [], []
    for k in range(steps):
        xs.append(x)
        zs.append(lqi.z.copy())
        cmd.append(lqi.step(x, refs[:, k]))
        x = advance(x, act(cmd[-1]))
    xs_, cmd_, zs_ = np.stack(xs, 1), np.stack(cmd, 1), np.stack(zs, 1)
    per = steps - 3 + 1
    prev = np.concatenate([np.zeros((2, 1)), cmd_[:, :-1]], axis=1)[:, :per]
    np.testing.assert_allclose(w.state[:, -1, -1], prev.reshape(-1), rtol=1e-6, atol=1e-6)
    visited = xs_[:, :per].reshape(-1, plant.order)
    np.testing.assert_allclose(w.state[:, -1, : plant.order], visited, rtol=1e-5, atol=1e-5)
    g = design_lqi(plant)
    law = -(xs_ @ g.Kx) - g.Ki * zs_
    np.testing.assert_allclose(w.target[:, 0], law[:, :per].reshape(-1), rtol=1e-5, atol=1e-5)
    plain, _ = aggregate(plant, amps, steps)
    assert np.abs(plain.state - w.state).max() > 0.05  # the actuator moved the rollouts
    still, _ = aggregate(plant, amps, steps, actuator={plant.name: (0.0, 0.0)})
    assert np.array_equal(still.state, plain.state)  # none at all: the plain rollouts
