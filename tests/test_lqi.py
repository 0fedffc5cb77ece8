"""LQI design against independent references: a hand-built Riccati solution and python-control."""

import control
import numpy as np
import pytest
from scipy.linalg import solve_continuous_are

from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.plants.config import plant_from_config
from generalist_control.plants.definition import PlantConfigError
from generalist_control.simulation.lqi import (
    LQIController,
    augment,
    design_lqi,
    sampled_closed_loop,
)
from generalist_control.simulation.simulate import discretise, simulate

PAPER_LINEAR = ["cstr", "unstable", "boeing747", "hydraulic_actuator", "two_mass_spring"]


def linear_cfg(A, B, C, Q=None, R=1.0):
    n = len(A)
    return {
        "tag": 0,
        "description": "test plant",
        "source": "test",
        "dt": 0.05,
        "states": [{"name": f"x{i}", "unit": "-"} for i in range(n)],
        "input": {"name": "u", "unit": "-"},
        "output": {"name": "y", "unit": "-"},
        "A": A,
        "B": B,
        "C": C,
        "lqi": {"Q": Q if Q is not None else [1.0] * (n + 1), "R": R},
    }


@pytest.mark.parametrize("name", PAPER_LINEAR)
def test_gains_equal_hand_built_riccati(name):
    p = load_plant(name)
    n = p.order
    # hand-built augmented system for [x; z], dz/dt = r - C x
    Aa = np.zeros((n + 1, n + 1))
    Aa[:n, :n] = p.A
    Aa[n, :n] = -p.C[0]
    Ba = np.zeros((n + 1, 1))
    Ba[:n] = p.B
    P = solve_continuous_are(Aa, Ba, p.Q, p.R)
    K = np.linalg.solve(p.R, Ba.T @ P)
    g = design_lqi(p)
    np.testing.assert_allclose(g.K, K, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(g.P, P, rtol=1e-7, atol=1e-10)
    assert np.all(np.linalg.eigvals(Aa - Ba @ K).real < 0)


@pytest.mark.parametrize("name", PAPER_LINEAR)
def test_gains_match_python_control_integral_action(name):
    # python-control integrates +C x, so with a diagonal Q its integral gain flips sign.
    p = load_plant(name)
    assert np.count_nonzero(p.Q - np.diag(np.diag(p.Q))) == 0
    K_pc, _, _ = control.lqr(control.ss(p.A, p.B, p.C, 0), p.Q, p.R, integral_action=p.C)
    g = design_lqi(p)
    np.testing.assert_allclose(g.Kx, np.asarray(K_pc)[0, :-1], rtol=1e-7)
    np.testing.assert_allclose(g.Ki, -np.asarray(K_pc)[0, -1], rtol=1e-7)


@pytest.mark.parametrize("name", available_plants())
def test_design_is_python_controls_lqr_bit_for_bit(name):
    """The design no longer imports python-control; its numbers are still lqr's, exactly."""
    p = load_plant(name)
    K, P, poles = control.lqr(*augment(p.A, p.B, p.C), p.Q, p.R)
    g = design_lqi(p)
    np.testing.assert_array_equal(g.Kx, np.asarray(K)[0, :-1])
    assert g.Ki == float(np.asarray(K)[0, -1])
    np.testing.assert_array_equal(g.P, P)
    np.testing.assert_array_equal(g.poles, poles)


def test_sampled_loop_matches_hand_built_discrete_system():
    p = load_plant("two_mass_spring")
    g = design_lqi(p)
    Ad, Bd = control.c2d(control.ss(p.A, p.B, p.C, 0), p.dt, "zoh").A, None
    Bd = np.asarray(control.c2d(control.ss(p.A, p.B, p.C, 0), p.dt, "zoh").B)
    n = p.order
    Phi = np.block([[Ad - Bd @ g.Kx[None, :], -Bd * g.Ki], [-p.dt * p.C, np.ones((1, 1))]])
    np.testing.assert_allclose(sampled_closed_loop(p, g), Phi, rtol=1e-9, atol=1e-12)
    assert np.abs(np.linalg.eigvals(Phi)).max() < 1
    # closed-loop response to a unit step via python-control's discrete simulation
    Gam = np.zeros((n + 1, 1))
    Gam[n, 0] = p.dt
    Cout = np.hstack([p.C, np.zeros((1, 1))])
    sysd = control.ss(Phi, Gam, Cout, 0, p.dt)
    steps = 200
    _, y_ref = control.forced_response(sysd, T=np.arange(steps + 1) * p.dt, U=np.ones(steps + 1))
    tr = simulate(p, LQIController(p, g), np.ones((1, steps)))
    np.testing.assert_allclose(tr.y[0], y_ref, rtol=1e-8, atol=1e-10)


def test_discretise_matches_python_control_zoh():
    p = load_plant("hydraulic_actuator")
    Ad, Bd = discretise(p.A, p.B, p.dt)
    ref = control.c2d(control.ss(p.A, p.B, p.C, 0), p.dt, "zoh")
    np.testing.assert_allclose(Ad, ref.A, rtol=1e-10)
    np.testing.assert_allclose(Bd, ref.B, rtol=1e-10)


@pytest.mark.parametrize("unit", [1.0, 1e-6, 1e6])
def test_zero_at_origin_is_unfit_in_any_units(unit):
    # velocity output of a mass-spring-damper: transfer s / (s^2 + s + 1), zero at s = 0;
    # `unit` rescales input and output (e.g. N -> MN, m -> um): still a zero at s = 0
    p = plant_from_config("velocity", linear_cfg([[0, 1], [-1, -1]], [[0], [unit]], [[0, unit]]))
    with pytest.raises(PlantConfigError, match="transmission zero at s = 0"):
        design_lqi(p)


@pytest.mark.parametrize("unit", [1e-6, 1e6])
def test_fitness_does_not_depend_on_units(unit):
    # position output 1 / (s^2 + s + 1) in tiny or huge units: no zero at s = 0
    # the same loop in other units of u and y: weights rescaled alike, same closed loop
    A, B, C = [[0, 1], [-1, -1]], [[0], [unit]], [[unit, 0]]
    p = plant_from_config("position", linear_cfg(A, B, C, Q=[1, 1, 1 / unit**2], R=unit**2))
    ref = design_lqi(plant_from_config("position", linear_cfg(A, [[0], [1]], [[1, 0]])))
    np.testing.assert_allclose(np.sort_complex(design_lqi(p).poles), np.sort_complex(ref.poles))


def test_unstabilisable_is_unfit():
    # unstable mode at s = 1 that the input cannot reach
    p = plant_from_config("uncontrollable", linear_cfg([[1, 0], [0, -1]], [[0], [1]], [[1, 1]]))
    with pytest.raises(PlantConfigError, match="not stabilisable"):
        design_lqi(p)


def test_too_fast_for_the_sample_time_is_rejected():
    # very cheap control: continuous loop stable, but its poles are far beyond 1/dt
    p = plant_from_config(
        "fast", linear_cfg([[0, 1], [0, 0]], [[0], [1]], [[1, 0]], Q=[1e8, 1, 1e10], R=1e-6)
    )
    with pytest.raises(PlantConfigError, match="sampled at dt"):
        design_lqi(p)


@pytest.mark.parametrize(
    ("patch", "match"),
    [
        ({"lqi": {"Q": [1, 1], "R": 1}}, r"lqi.Q' has shape \(2,\)"),
        ({"lqi": {"Q": [1, -1, 1], "R": 1}}, "lqi.Q' is not positive semidefinite"),
        ({"lqi": {"Q": [[1, 2, 0], [0, 1, 0], [0, 0, 1]], "R": 1}}, "not symmetric"),
        ({"lqi": {"Q": [1, 1, 1], "R": 0}}, "lqi.R' must be positive definite"),
        ({"lqi": {"Q": [1, 1, 1], "R": [1, 2]}}, "lqi.R' has shape"),
        ({"A": [[0, 1], [0, float("nan")]]}, "field 'A' contains NaN"),
        ({"B": [[0], [1], [2]]}, r"field 'B' has shape \(3, 1\), expected \(2, 1\)"),
        ({"lqi": {"Q": [1, 1, 1]}}, "needs 'Q' and 'R'"),
        ({"dt": 0}, "'dt' must be positive"),
    ],
)
def test_bad_plant_config_errors_name_the_field(patch, match):
    cfg = linear_cfg([[0, 1], [-1, -1]], [[0], [1]], [[1, 0]])
    cfg.update(patch)
    with pytest.raises(PlantConfigError, match=match):
        plant_from_config("bad", cfg)


def test_missing_field_and_bad_function_path():
    cfg = linear_cfg([[0, 1], [-1, -1]], [[0], [1]], [[1, 0]])
    del cfg["tag"]
    with pytest.raises(PlantConfigError, match="plant 'bad': missing field 'tag'"):
        plant_from_config("bad", cfg)
    cfg = linear_cfg([[0, 1], [-1, -1]], [[0], [1]], [[1, 0]])
    del cfg["states"]  # a catalogue plant names its signals; the message says how
    with pytest.raises(PlantConfigError, match=r"missing field 'states' \(one \{name, unit\} per"):
        plant_from_config("bad", cfg)
    cfg = linear_cfg([[0, 1], [-1, -1]], [[0], [1]], [[1, 0]])
    cfg["dynamics"] = {"f": "no.such.module.f", "x_op": [0, 0]}
    with pytest.raises(PlantConfigError, match="dynamics.f"):
        plant_from_config("bad", cfg)
