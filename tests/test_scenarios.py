"""Evaluation scenarios: reference shapes, initial states, perturbations and config errors."""

import numpy as np
import pytest
from omegaconf import OmegaConf

from generalist_control.catalog import load_plant
from generalist_control.scenarios import ScenarioError, perturbation, references
from generalist_control.simulate import Perturbation


def test_reference_shapes_and_values():
    p = load_plant("two_mass_spring")
    r, x0 = references("s", {"kind": "step", "amplitude": 2.0, "duration": 10.0}, p)
    assert r.shape == (1, 200) and np.all(r == 2.0) and x0 is None
    r, _ = references("rs", {"kind": "random_steps", "count": 5, "limit": 20, "seed": 1}, p)
    assert r.shape[0] == 5 and np.all(np.abs(r) <= 20) and np.all(r == r[:, :1])
    grid = np.round(np.arange(-20, 20.01, 0.2), 6)
    assert not np.isin(np.round(r[:, 0], 6), grid).any()  # off the training grid
    r2, _ = references("rs", {"kind": "random_steps", "count": 5, "limit": 20, "seed": 1}, p)
    np.testing.assert_array_equal(r, r2)
    r, _ = references("ramp", {"kind": "ramp", "slope": 0.5, "duration": 4.0}, p)
    np.testing.assert_allclose(r[0], 0.5 * np.arange(80) * 0.05)


def test_sine_starts_from_the_requested_output():
    p = load_plant("hydraulic_actuator")
    r, x0 = references("sine", {"kind": "sine", "omega": 0.5, "y0": 0.5, "duration": 5}, p)
    assert x0.shape == (1, 3) and p.output(x0)[0] == pytest.approx(0.5)
    np.testing.assert_allclose(r[0], np.sin(0.5 * np.arange(100) * 0.05))


def test_composite_is_step_then_ramp_then_sine():
    p = load_plant("cstr")
    r, _ = references("c", {"kind": "composite", "amplitude": 1.0, "duration": 30.0}, p)
    t = np.arange(600) * 0.05
    assert np.all(r[0, t < 9.9] == 1.0)
    assert r[0, 300] == pytest.approx(2.0, abs=0.02)  # t = 15 s: halfway up the ramp
    assert np.ptp(r[0, t > 21]) > 1.5


def test_perturbation_and_errors():
    assert perturbation("x", {"perturbation": {"u_limit": 0.5}}) == Perturbation(u_limit=0.5)
    assert perturbation("x", {}) is None
    with pytest.raises(ScenarioError, match="scenario 'x': bad perturbation field"):
        perturbation("x", {"perturbation": {"u_lim": 0.5}})
    with pytest.raises(ScenarioError, match="scenario 'y': kind 'spiral'"):
        references("y", {"kind": "spiral"}, load_plant("cstr"))


def test_default_scenarios_are_valid():
    from generalist_control.paths import conf_dir

    specs = OmegaConf.to_container(OmegaConf.load(conf_dir() / "evaluation/default.yaml"))
    for name, spec in specs["scenarios"].items():
        references(name, spec, load_plant("cstr"))
        perturbation(name, spec)
