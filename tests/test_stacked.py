"""One loop for many batches (simulation.stacked): each run's numbers are its own loop's."""

import dataclasses
from functools import partial

import numpy as np
import pytest

from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.crazyflie import fly_many
from generalist_control.simulation.lqi import AntiWindupLQIController, LQIController
from generalist_control.simulation.perturbation import Perturbation
from generalist_control.simulation.references import state_envelope, state_envelopes
from generalist_control.simulation.simulate import (
    PerPlantController,
    Run,
    Segment,
    controller_rows,
    simulate,
    simulate_many,
    simulate_stacked,
)

#: Linear plants of orders 2 and 4 and a nonlinear one (RK4).
PLANTS = ("cstr", "two_mass_spring", "two_tank")


def _runs(rows: int = 2) -> list[Run]:
    """Runs of several lengths, from rest and not, under every kind of perturbation."""
    rng = np.random.default_rng(5)
    perts = [
        None,
        Perturbation(u_limit=0.4, rate_limit=2.0),
        Perturbation(actuator_gain=0.8, disturbance=0.1, disturbance_start=0.5),
        Perturbation(noise_std=(0.01, 0.02, 0.01, 0.02), noise_start=0.3, seed=4),
    ]
    runs = []
    for i, name in enumerate(PLANTS):
        p = load_plant(name)
        for j, pert in enumerate(perts):
            steps = 30 + 7 * ((i + j) % 3)
            r = rng.uniform(-2, 2, size=(rows, 1)) * np.ones((1, steps)) * p.amplitude_scale
            x0 = rng.uniform(-0.1, 0.1, size=(rows, p.order)) if j % 2 else None
            if pert is not None and pert.noise_std is not None:
                pert = Perturbation(noise_std=pert.noise_std[: p.order], noise_start=0.3, seed=4)
            runs.append(Run(p, r, x0, pert))
    return runs


def _same(a, b) -> None:
    for field in ("t", "x", "u", "r", "y", "diverged"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)


def test_every_run_is_its_own_loop_bit_for_bit():
    """Two controllers, four perturbations, three plants, runs of three lengths: one loop."""
    runs = _runs()
    limits = Perturbation(u_limit=0.3)
    aw = partial(AntiWindupLQIController, limits=limits)
    got = simulate_stacked(
        [Segment(PerPlantController(LQIController), runs), Segment(PerPlantController(aw), runs)]
    )
    for i, run in enumerate(runs):
        _same(got[0][i], simulate_many([run], PerPlantController(LQIController))[0])
        _same(got[1][i], simulate_many([run], PerPlantController(aw))[0])


def test_a_run_alone_in_its_loop_differs_at_most_in_the_last_bits():
    """BLAS multiplies one row by another path than several: 1 ulp a sample, not more."""
    run = Run(load_plant("two_mass_spring"), np.ones((1, 200)))
    other = Run(run.plant, np.full((1, 50), -1.0))
    (got, _), *_ = simulate_stacked([Segment(PerPlantController(LQIController), [run, other])])
    alone = simulate_many([run], PerPlantController(LQIController))[0]
    np.testing.assert_allclose(got.x, alone.x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(got.u, alone.u, rtol=1e-12, atol=1e-14)


class _Recorder:
    """LQI that records which of its rows were told their runs ended."""

    def __init__(self) -> None:
        self.inner, self.finished = PerPlantController(LQIController), []

    def reset(self, plants, counts):
        self.inner.reset(plants, counts)

    def step(self, x, r):
        return self.inner.step(x, r)

    def finish(self, rows):
        self.finished.append(sorted(rows.tolist()))


def test_runs_end_on_their_own_sample_and_their_controller_is_told():
    p, q = load_plant("cstr"), load_plant("two_tank")
    runs = [Run(p, np.ones((2, 10))), Run(q, np.ones((1, 25))), Run(p, np.ones((3, 25)))]
    rec = _Recorder()
    ended = []
    (trajs,) = simulate_stacked([Segment(rec, runs)], on_end=lambda k, d: ended.append((k, d)))
    assert [tr.u.shape for tr in trajs] == [(2, 10), (1, 25), (3, 25)]
    assert [tr.x.shape[1] for tr in trajs] == [11, 26, 26]
    assert ended == [(10, [(0, 0)]), (25, [(0, 1), (0, 2)])]
    rows = controller_rows([Segment(rec, runs)])[0]
    assert rows[0] == slice(0, 2)  # cstr's runs first (plants in order of first appearance)
    assert rec.finished[0] == [0, 1] and rec.finished[1] == [2, 3, 4, 5]


def test_runs_of_other_sample_times_are_refused():
    p = load_plant("cstr")
    q = dataclasses.replace(p, dt=2 * p.dt)
    runs = [Run(p, np.ones((1, 5))), Run(q, np.ones((1, 5)))]
    with pytest.raises(ValueError, match="one sample time"):
        simulate_stacked([Segment(PerPlantController(LQIController), runs)])


def test_envelopes_in_one_loop_are_one_simulation_each():
    plants = [load_plant(n) for n in PLANTS]
    many = state_envelopes([(p, a) for p in plants for a in (1.0, 3.0)])
    for (p, a), env in zip([(p, a) for p in plants for a in (1.0, 3.0)], many, strict=True):
        steps, amp = 200, a * p.amplitude_scale
        tr = simulate(p, LQIController(p), np.array([[amp] * steps, [-amp] * steps]))
        np.testing.assert_array_equal(env, np.abs(tr.x).max(axis=(0, 1)))
        np.testing.assert_array_equal(state_envelope(p, a), env)


def test_the_crazyflie_flies_several_controllers_on_the_same_noise():
    p = load_plant("crazyflie_altitude")
    r = np.full((3, 300), 1.0)
    both = fly_many([LQIController(p), PerRowGain(LQIController(p), 0.7)], r, seed=2)
    _same(both[0], fly_many([LQIController(p)], r, seed=2)[0])
    _same(both[1], fly_many([PerRowGain(LQIController(p), 0.7)], r, seed=2)[0])


class PerRowGain:
    """A controller scaled by ``gain``: another law on the same vehicle."""

    def __init__(self, inner, gain: float) -> None:
        self.inner, self.gain = inner, gain

    def reset(self, batch_size: int) -> None:
        self.inner.reset(batch_size)

    def step(self, x, r):
        return self.gain * self.inner.step(x, r)
