"""Evaluation scenarios: reference shapes, initial states, perturbations and config errors."""

from dataclasses import replace

import numpy as np
import pytest
from omegaconf import OmegaConf

from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.perturbation import Perturbation
from generalist_control.simulation.references import (
    FAMILIES,
    family_references,
    family_spec,
    state_envelope,
    visited_moment,
)
from generalist_control.simulation.scenarios import (
    ScenarioError,
    perturbation,
    references,
    with_state_draw,
)


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
    """Every scenario of conf/evaluation/default.yaml builds the documented signals.

    Checked on the plants it names, or else on plants of different order and amplitude
    scale; each kind's shape is recomputed here from the spec (amplitudes times the plant's
    ``amplitude_scale``), and a perturbation is built exactly when the spec gives one.
    """
    from dataclasses import fields

    from generalist_control.common.paths import conf_dir

    specs = OmegaConf.to_container(OmegaConf.load(conf_dir() / "evaluation/default.yaml"))
    scenarios = specs["scenarios"]
    kinds = {spec["kind"] for spec in scenarios.values()}
    assert kinds == {
        "step", "random_steps", "sine", "ramp", "composite", "staircase", "sweep", "hold"
    }  # fmt: skip
    default_plants = ("cstr", "two_mass_spring", "magnetic_levitation")  # orders 2, 4, 3
    assert {load_plant(n).amplitude_scale for n in default_plants} == {1.0, 0.1}
    for name, spec in scenarios.items():
        for plant_name in spec.get("plants") or default_plants:
            p = load_plant(plant_name)
            r, x0 = references(name, spec, p)
            n_steps = round(spec["duration"] / p.dt)
            rows = spec.get("count", 8 if spec["kind"] != "sweep" else 1)
            rows = rows if spec["kind"] in ("random_steps", *FAMILIES) else 1
            where = f"{name} on {plant_name}"
            assert r.shape == (rows, n_steps), where
            assert np.all(np.isfinite(r)), where
            t = np.arange(n_steps) * p.dt
            s = p.amplitude_scale
            amp = spec.get("amplitude", 1.0) * s
            if spec["kind"] == "step":
                np.testing.assert_array_equal(r, np.full((1, n_steps), amp), err_msg=where)
            elif spec["kind"] == "random_steps":
                assert np.all(r == r[:, :1]), where  # each run is one constant step
                assert np.all(np.abs(r) <= spec["limit"] * s) and np.all(r != 0), where
                assert len(np.unique(r[:, 0])) == rows, where
                assert np.ptp(r[:, 0]) > 0.5 * spec["limit"] * s, where  # spread over +-limit
                again, _ = references(name, spec, p)
                np.testing.assert_array_equal(again, r, err_msg=where)  # seeded
            elif spec["kind"] == "sine":
                want = amp * np.sin(spec["omega"] * t)
                np.testing.assert_allclose(r[0], want, rtol=0, atol=1e-12, err_msg=where)
                assert x0.shape == (1, p.order), where
                assert p.output(x0)[0] == pytest.approx(spec["y0"] * s, rel=1e-12), where
            elif spec["kind"] == "ramp":
                want = spec["slope"] * s * t
                np.testing.assert_allclose(r[0], want, rtol=1e-12, atol=0, err_msg=where)
            elif spec["kind"] in FAMILIES:
                _check_family(spec, p, r, x0, t, where)
            else:  # composite: step to A for a third, ramp to 3 A, then a sine about 3 A
                third = t[-1] / 3
                first, middle = t < third, (t >= third) & (t <= 2 * third)
                last = t > 2 * third
                np.testing.assert_array_equal(r[0, first], amp, err_msg=where)
                np.testing.assert_allclose(
                    r[0, middle], amp * (1 + 2 * (t[middle] - third) / third), rtol=1e-12
                )
                sine = 3 * amp + amp * np.sin(spec["omega"] * (t[last] - 2 * third))
                np.testing.assert_allclose(r[0, last], sine, rtol=1e-12, atol=1e-12 * amp)
            if spec["kind"] not in ("sine", *FAMILIES):
                assert x0 is None, where  # from rest
            pert = perturbation(name, spec, p)
            if "perturbation" not in spec:
                assert pert is None, where
                continue
            assert isinstance(pert, Perturbation), where
            given = spec["perturbation"]
            defaults = Perturbation()
            if "noise_rel" in given:  # relative to the plant's unit-step state envelope
                want_std = given["noise_rel"] * state_envelope(p, 1.0)
                np.testing.assert_allclose(pert.noise_std, want_std, rtol=1e-12)
                given = {k: v for k, v in given.items() if k != "noise_rel"}
                given["noise_std"] = pert.noise_std
            for f in fields(Perturbation):
                want = given.get(f.name, getattr(defaults, f.name))
                want = tuple(want) if isinstance(want, list) else want
                assert getattr(pert, f.name) == want, (where, f.name)


def _check_family(spec, p, r, x0, t, where):
    """A randomised family's documented shape (simulation/references.py), from its spec."""
    s = p.amplitude_scale
    count = r.shape[0]
    assert x0.shape == (count, p.order), where
    env = state_envelope(p, spec.get("x0_amplitude", 3.0)) * spec.get("x0_scale", 1.0)
    share = spec.get("x0_fraction", 1.0 if spec["kind"] == "hold" else 0.0)
    n_random = round(share * count)
    assert np.all(np.abs(x0) <= env + 1e-12), where
    assert np.all(np.abs(x0[:n_random]).max(axis=1) > 0), where
    assert np.all(x0[n_random:] == 0), where
    if spec["kind"] == "staircase":
        n = spec["levels"]
        for row in r:
            segments = np.array_split(row, n)
            assert all(np.all(seg == seg[0]) for seg in segments), where
            assert len({seg[0] for seg in segments}) == n, where
        assert np.all(np.abs(r) <= spec["limit"] * s), where
    elif spec["kind"] == "sweep":
        w0, w1 = spec["omega"]
        angle = w0 * t + 0.5 * (w1 - w0) * t**2 / t[-1]
        want = spec.get("amplitude", 1.0) * s * np.sin(angle)
        np.testing.assert_allclose(r[0], want, rtol=0, atol=1e-12, err_msg=where)
    elif spec["kind"] == "hold":
        assert np.all(r == r[:, :1]) and np.all(np.abs(r) <= spec["limit"] * s), where
    again, x0_again = references("again", spec, p)
    np.testing.assert_array_equal(again, r, err_msg=where)  # seeded
    np.testing.assert_array_equal(x0_again, x0, err_msg=where)


def test_visited_initial_states_are_the_same_in_any_state_coordinates():
    """``x0_draw: visited`` draws with the visited states' second moment, so a plant in other
    coordinates ``x' = T x`` gets ``T``'s image of the same distribution (a box would not)."""
    p = load_plant("two_mass_spring")
    n = p.order
    T = np.eye(n) + 0.8 * np.random.default_rng(3).standard_normal((n, n))
    Ti = np.linalg.inv(T)
    Q = p.Q.copy()
    Q[:n, :n], Q[:n, n:], Q[n:, :n] = Ti.T @ p.Q[:n, :n] @ Ti, Ti.T @ p.Q[:n, n:], p.Q[n:, :n] @ Ti
    moved = replace(p, name="moved", A=T @ p.A @ Ti, B=T @ p.B, C=p.C @ Ti, Q=Q)
    m, m_moved = visited_moment(p, 3.0), visited_moment(moved, 3.0)
    np.testing.assert_allclose(m_moved, T @ m @ T.T, rtol=1e-6, atol=1e-9 * np.abs(m_moved).max())
    spec = {"kind": "hold", "count": 20000, "x0_draw": "visited", "x0_scale": 0.5}
    _, x0 = family_references(moved, spec, 10)
    sample = x0.T @ x0 / len(x0)
    assert np.linalg.norm(sample - 0.25 * m_moved) < 0.05 * np.linalg.norm(0.25 * m_moved)
    _, again = family_references(moved, spec, 10)
    np.testing.assert_array_equal(x0, again)  # seeded
    with pytest.raises(ValueError, match="x0_draw must be one of box, visited, got 'ball'"):
        family_spec({"kind": "hold", "x0_draw": "ball"})
    noisy = {"kind": "step", "perturbation": {"noise_rel": 0.01, "seed": 0}}
    drawn = with_state_draw({"s": {"kind": "step"}, "h": {"kind": "hold"}, "n": noisy}, "visited")
    assert drawn == {
        "s": {"kind": "step"},
        "h": {"kind": "hold", "x0_draw": "visited"},
        "n": {
            "kind": "step",
            "perturbation": {"noise_rel": 0.01, "seed": 0, "noise_draw": "visited"},
        },
    }
    # relative state noise in drawn coordinates: covariance 0.01^2 x the unit-step moment
    for plant, moment in ((p, visited_moment(p, 1.0)), (moved, visited_moment(moved, 1.0))):
        pert = perturbation("n", drawn["n"], plant)
        assert pert is not None and np.shape(pert.noise_std) == (n, n)
        root = np.array(pert.noise_std)
        np.testing.assert_allclose(root @ root.T, 1e-4 * moment, atol=1e-12 * np.abs(moment).max())
        z = np.random.default_rng(0).standard_normal((5, n))
        np.testing.assert_allclose(pert.noise(z), z @ root.T)
    np.testing.assert_allclose(visited_moment(moved, 1.0), T @ visited_moment(p, 1.0) @ T.T,
                               rtol=1e-6)  # fmt: skip
    with pytest.raises(ScenarioError, match="noise_draw must be one of box, visited"):
        perturbation("n", {"perturbation": {"noise_rel": 0.01, "noise_draw": "ball"}}, p)
