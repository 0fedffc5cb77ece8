"""The simulator: exact ZOH for linear plants, RK4 for nonlinear, divergence detection."""

import numpy as np
import pytest

from generalist_control.plants.catalog import load_plant
from generalist_control.plants.definition import Plant, Signal
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import simulate

A = np.array([[0.0, 1.0], [-2.0, -0.5]])
B = np.array([[0.0], [1.0]])


def linear_as_nonlinear(x, u):
    return x @ A.T + u[:, None] * B[:, 0]


def make_plant(f=None):
    return Plant(
        name="msd",
        tag=0,
        description="",
        source="",
        dt=0.05,
        states=(Signal("p", "m"), Signal("v", "m/s")),
        input_signal=Signal("u", "N"),
        output_signal=Signal("p", "m"),
        A=A,
        B=B,
        C=np.array([[1.0, 0.0]]),
        Q=np.eye(3),
        R=np.eye(1),
        f=f,
        x_op=np.zeros(2),
        substeps=20,
    )


class OpenLoop:
    def __init__(self, u):
        self.u, self.k = u, 0

    def reset(self, batch_size):
        self.k = 0

    def step(self, x, r):
        self.k += 1
        return self.u[:, self.k - 1]


def test_rk4_matches_exact_zoh_on_a_linear_plant():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(3, 100))
    x0 = rng.normal(size=(3, 2))
    exact = simulate(make_plant(), OpenLoop(u), np.zeros((3, 100)), x0=x0)
    rk4 = simulate(make_plant(linear_as_nonlinear), OpenLoop(u), np.zeros((3, 100)), x0=x0)
    np.testing.assert_allclose(rk4.x, exact.x, atol=1e-9)


def test_free_response_matches_matrix_exponential():
    from scipy.linalg import expm

    x0 = np.array([[1.0, 0.0]])
    tr = simulate(make_plant(), OpenLoop(np.zeros((1, 40))), np.zeros((1, 40)), x0=x0)
    np.testing.assert_allclose(tr.x[0, 40], expm(A * 40 * 0.05) @ x0[0], rtol=1e-10)


def test_batched_runs_equal_single_runs():
    p = load_plant("cstr")
    amps = np.array([-3.0, 0.5, 12.0])
    batch = simulate(p, LQIController(p), np.repeat(amps[:, None], 80, axis=1))
    for i, a in enumerate(amps):
        one = simulate(p, LQIController(p), np.full((1, 80), a))
        np.testing.assert_allclose(batch.x[i], one.x[0], rtol=1e-12, atol=1e-12)
    # linearity: the response scales with the amplitude
    np.testing.assert_allclose(batch.y[2] / 12.0, batch.y[1] / 0.5, rtol=1e-9, atol=1e-12)


class Destabilising:
    def reset(self, batch_size):
        pass

    def step(self, x, r):
        return 50.0 * x[:, 0] + 50.0 * x[:, 1]


def test_divergence_is_detected_and_frozen():
    p = load_plant("unstable")
    tr = simulate(p, Destabilising(), np.ones((2, 400)), x0=np.array([[0.1, 0.0], [0.0, 0.0]]))
    assert tr.diverged.tolist() == [True, False]
    assert np.all(np.isfinite(tr.x))


def test_x0_shape_error():
    p = load_plant("cstr")
    with pytest.raises(ValueError, match=r"x0 has shape \(1, 3\); plant 'cstr' needs \(1, 2\)"):
        simulate(p, LQIController(p), np.ones((1, 10)), x0=np.zeros((1, 3)))


def test_actuator_limits_are_respected():
    from generalist_control.simulation.perturbation import Perturbation

    p = load_plant("cstr")
    amp = simulate(
        p, LQIController(p), np.full((2, 200), 5.0), perturbation=Perturbation(u_limit=0.3)
    )
    assert np.abs(amp.u).max() == pytest.approx(0.3)
    rate = simulate(
        p, LQIController(p), np.full((1, 200), 5.0), perturbation=Perturbation(rate_limit=0.5)
    )
    assert np.abs(np.diff(np.concatenate([[0.0], rate.u[0]]))).max() <= 0.5 * p.dt + 1e-12


def test_noise_is_seeded_and_starts_on_time():
    from generalist_control.simulation.perturbation import Perturbation

    p = load_plant("cstr")
    pert = Perturbation(noise_std=0.05, noise_start=2.0, seed=3)
    a = simulate(p, LQIController(p), np.ones((1, 100)), perturbation=pert)
    b = simulate(p, LQIController(p), np.ones((1, 100)), perturbation=pert)
    clean = simulate(p, LQIController(p), np.ones((1, 100)))
    np.testing.assert_array_equal(a.x, b.x)
    k0 = int(round(2.0 / p.dt))
    np.testing.assert_array_equal(a.u[:, :k0], clean.u[:, :k0])
    assert not np.allclose(a.u[:, k0:], clean.u[:, k0:])


def test_integral_action_rejects_a_constant_input_disturbance():
    from generalist_control.simulation.perturbation import Perturbation

    p = load_plant("cstr")
    pert = Perturbation(disturbance=0.5, disturbance_start=5.0)
    tr = simulate(p, LQIController(p), np.ones((1, 600)), perturbation=pert)
    k0 = int(round(5.0 / p.dt))
    assert np.abs(tr.y[0, k0 + 20 : k0 + 80] - 1).max() > 1e-3  # the disturbance is felt
    assert tr.y[0, -1] == pytest.approx(1.0, abs=1e-4)  # and rejected
    # u cancels it (the recorded u excludes the disturbance): steady u = 1 / G(0) - 0.5
    u_nominal = 1.0 / float((-p.C @ np.linalg.solve(p.A, p.B))[0, 0])
    assert tr.u[0, -1] == pytest.approx(u_nominal - 0.5, abs=1e-4)


def test_anti_windup_equals_lqi_without_limits_and_helps_with_them():
    from generalist_control.simulation.lqi import AntiWindupLQIController
    from generalist_control.simulation.metrics import step_metrics
    from generalist_control.simulation.perturbation import Perturbation

    p = load_plant("cstr")
    free = Perturbation()
    a = simulate(p, AntiWindupLQIController(p, free), np.full((2, 200), 3.0), perturbation=free)
    b = simulate(p, LQIController(p), np.full((2, 200), 3.0))
    np.testing.assert_allclose(a.u, b.u, rtol=1e-12, atol=1e-14)
    pert = Perturbation(rate_limit=0.5)
    r = np.ones((1, 600))
    plain = simulate(p, LQIController(p), r, perturbation=pert)
    aw = simulate(p, AntiWindupLQIController(p, pert), r, perturbation=pert)
    os_plain = step_metrics(plain.t, plain.y, plain.u, 1.0)["overshoot"][0]
    os_aw = step_metrics(aw.t, aw.y, aw.u, 1.0)["overshoot"][0]
    assert os_aw < 0.5 * os_plain


def test_simulate_many_equals_separate_runs():
    from generalist_control.simulation.lqi import AntiWindupLQIController
    from generalist_control.simulation.perturbation import Perturbation
    from generalist_control.simulation.simulate import PerPlantController, Run, simulate_many

    plants = [load_plant(n) for n in ("cstr", "hydraulic_actuator", "two_mass_spring")]
    pert = Perturbation(u_limit=0.4, noise_std=0.01, seed=5)
    runs = [
        Run(plants[0], np.full((2, 120), 2.0)),
        Run(plants[1], np.full((1, 120), -1.0), x0=np.array([[0.1, 0.0, 0.0]])),
        Run(plants[2], np.full((3, 120), 0.5), perturbation=pert),
    ]
    many = simulate_many(runs, PerPlantController(lambda p: AntiWindupLQIController(p, pert)))
    for run, tr in zip(runs, many, strict=True):
        one = simulate(
            run.plant, AntiWindupLQIController(run.plant, pert), run.r, run.x0, run.perturbation
        )
        np.testing.assert_array_equal(tr.x, one.x)
        np.testing.assert_array_equal(tr.u, one.u)
    with pytest.raises(ValueError, match="equal length"):
        simulate_many(
            [runs[0], Run(plants[1], np.ones((1, 50)))], PerPlantController(LQIController)
        )


def test_actuator_gain_scales_what_the_plant_receives_not_what_is_recorded():
    from generalist_control.simulation.perturbation import Perturbation
    from generalist_control.simulation.simulate import simulate

    p = load_plant("two_mass_spring")

    class Constant:
        def reset(self, batch_size):
            pass

        def step(self, x, r):
            return np.full(x.shape[0], 0.3)

    r = np.zeros((1, 40))
    nominal = simulate(p, Constant(), r)
    strong = simulate(p, Constant(), r, perturbation=Perturbation(actuator_gain=1.2))
    np.testing.assert_array_equal(strong.u, nominal.u)  # the delivered command is recorded
    # a linear plant from rest: the response to 1.2 u is 1.2 times the response to u
    np.testing.assert_allclose(strong.x, 1.2 * nominal.x, rtol=1e-12, atol=1e-15)
