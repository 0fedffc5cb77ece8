"""Plant families: drawn plants are what they claim, their LQI rule is python-control's LQR,
every refusal has its reason, and the same seed draws the same plants bit for bit."""

from __future__ import annotations

import dataclasses
import json

import control
import numpy as np
import pytest
from omegaconf import OmegaConf

from generalist_control.plants.definition import Plant, Signal
from generalist_control.plants.families import CLASSES, FORMS, LinearFamily, realise
from generalist_control.plants.lqi_weights import BrysonRule, NoBandwidthError, Weights
from generalist_control.simulation.family_draw import (
    REASONS,
    FamilyChecks,
    Rejected,
    check_design,
    draw_family,
    read_families,
    settling_times,
)
from generalist_control.simulation.lqi import LQIController, design_lqi, sampled_closed_loop
from generalist_control.simulation.metrics import step_metrics
from generalist_control.simulation.simulate import simulate
from helpers import compose_cfg

COUNT = 300  # plants of the default family drawn for the module


def _families(*overrides: str) -> dict:
    cfg = compose_cfg(*overrides, config="generate_families")
    return OmegaConf.to_container(cfg.families, resolve=True)


def _family(*overrides: str) -> tuple[LinearFamily, FamilyChecks]:
    family, settings = read_families(_families(*overrides))
    assert isinstance(family, LinearFamily)
    return family, settings.checks


@pytest.fixture(scope="module")
def drawn():
    family, checks = _family()
    return family, checks, draw_family(family, COUNT, checks)


def _poles_zeros(plant: Plant) -> tuple[np.ndarray, np.ndarray]:
    """Poles, and zeros as the roots of python-control's transfer-function numerator.

    Its leading coefficients below 1e-9 of the largest are rounding (``ss.zeros()`` turns
    them into spurious zeros near 1e4 .. 1e12 for a plant with none).
    """
    sys = control.ss(plant.A, plant.B, plant.C, 0)
    num = np.asarray(control.ss2tf(sys).num[0][0], dtype=float)
    num = num[np.argmax(np.abs(num) > 1e-9 * np.abs(num).max()) :]
    return np.asarray(sys.poles()), np.roots(num)


def test_drawn_plants_are_of_the_classes_they_claim(drawn):
    """Checked with python-control on the realised (A, B, C), in its own coordinates."""
    family, _, draw = drawn
    for d in draw.kept:
        p, classes = d.plant, set(d.candidate.model.classes)
        poles, zeros = _poles_zeros(p)
        tol = 1e-6 * max(1.0, np.abs(poles).max())
        at_zero = np.abs(poles) < tol
        with np.errstate(invalid="ignore"):  # damping of a pole at s = 0: 0 / 0
            _, zeta, _ = control.damp(control.ss(p.A, p.B, p.C, 0), doprint=False)
        pair = np.abs(poles.imag) > tol
        assert ("integrating" in classes) == bool(at_zero.any()), p.name
        assert ("unstable" in classes) == bool((poles.real > tol).any()), p.name
        assert ("nonminimum_phase" in classes) == bool((zeros.real > tol).any()), p.name
        light = pair & (zeta < family.damping[0])
        assert ("lightly_damped" in classes) == bool(light.any()), (p.name, zeta)
        slow = (zeros.real < -tol) & (np.abs(zeros) <= family.slow_zero[1])
        assert ("slow_zero" in classes) == bool(slow.any()), (p.name, zeros)
        if classes == {"well_damped"}:
            assert (poles.real < -tol).all() and (zeta[pair] >= family.damping[0] - 1e-9).all()
        assert p.order == d.candidate.model.order and 1 <= p.order <= 4


def test_drawn_plants_realise_their_model_poles_zeros_and_gain(drawn):
    _, _, draw = drawn
    for d in draw.kept:
        model, p = d.candidate.model, d.plant
        want = [q for q in model.poles for q in ((q, q.conjugate()) if q.imag > 0 else (q,))]
        poles, zeros = _poles_zeros(p)
        scale = max(1.0, np.abs(want).max())
        np.testing.assert_allclose(
            np.sort_complex(poles), np.sort_complex(want), atol=1e-6 * scale
        )
        np.testing.assert_allclose(np.sort(zeros.real), np.sort(model.zeros), rtol=1e-6, atol=1e-9)
        m = int(np.sum(np.abs(np.asarray(want)) == 0))  # integrators
        sys = control.ss(p.A, p.B, p.C, 0)
        if m == 0:
            assert float(control.dcgain(sys)) == pytest.approx(model.gain, rel=1e-6), p.name
        else:  # s^m G(s) near s = 0 (a double root at 0 comes out split by ~1e-8)
            got = complex(sys(1e-5j)) * 1e-5j**m
            assert got.real == pytest.approx(model.gain, rel=5e-3), p.name


def test_the_family_spans_gains_time_constants_orders_classes_and_forms(drawn):
    family, _, draw = drawn
    models = [d.candidate.model for d in draw.kept]
    gains = np.array([m.gain for m in models])
    decades = np.log10(np.abs(gains))
    assert decades.min() < -1.5 and decades.max() > 1.5  # 0.01 .. 100: four decades
    assert 0.35 < np.mean(gains > 0) < 0.65  # both signs
    high = []  # the high-frequency gain, s^r G(s) for s -> inf (relative degree r)
    for d in draw.kept:
        r, s = d.plant.order - len(d.candidate.model.zeros), 1e4j
        high.append(abs(complex(control.ss(d.plant.A, d.plant.B, d.plant.C, 0)(s)) * s**r))
    assert np.log10(max(high)) - np.log10(min(high)) > 6  # over several decades
    taus = [-1 / q.real for m in models for q in m.poles if q.imag == 0 and q.real < 0]
    assert min(taus) < 0.2 and max(taus) > 50  # 0.1 s .. 100 s
    assert {d.plant.order for d in draw.kept} == {1, 2, 3, 4}
    assert {c for m in models for c in m.classes} == set(CLASSES)
    assert {d.candidate.form for d in draw.kept} == set(FORMS)
    assert all(d.plant.dt == family.dt == 0.05 for d in draw.kept)


def test_the_rule_is_bryson_at_the_drawn_bandwidth_and_free_of_coordinates(drawn):
    """q_y |G(j w_c)|^2 = 1 (python-control's response); every form gives the same loop."""
    _, _, draw = drawn
    for d in draw.kept[:40]:
        w, p = d.candidate.weights, d.plant
        assert w is not None
        g = complex(control.ss(p.A, p.B, p.C, 0)(1j * w.bandwidth))
        assert w.q_y * abs(g) ** 2 == pytest.approx(1.0, rel=1e-9)
        assert w.q_z == pytest.approx((w.integral_ratio * w.bandwidth) ** 2 * w.q_y, rel=1e-12)
        poles = []
        for form in FORMS:
            A, B, C = realise(d.candidate.model, form, np.random.default_rng(0))
            Q, R = w.matrices(B, C)
            other = dataclasses.replace(p, A=A, B=B, C=C, Q=Q, R=R)
            poles.append(np.sort_complex(design_lqi(other).poles))
        for q in poles[1:]:
            np.testing.assert_allclose(q, poles[0], rtol=1e-6, atol=1e-8)


def test_the_rule_gives_the_loop_of_python_controls_lqr_on_the_hand_built_system(drawn):
    """The augmented system and its sampled loop built by hand, K from ``control.lqr``."""
    _, _, draw = drawn
    for d in draw.kept[:40]:
        p, w = d.plant, d.candidate.weights
        A, B, C, n = p.A, p.B, p.C, p.order
        Aa = np.block([[A, np.zeros((n, 1))], [-C, np.zeros((1, 1))]])  # dz/dt = r - y
        Ba = np.vstack([B, [[0.0]]])
        g = complex(control.ss(A, B, C, 0)(1j * w.bandwidth))
        Q = np.zeros((n + 1, n + 1))
        Q[:n, :n] = C.T @ C / abs(g) ** 2
        Q[n, n] = (w.integral_ratio * w.bandwidth) ** 2 / abs(g) ** 2
        K, _, _ = control.lqr(Aa, Ba, Q, np.eye(1))
        sysd = control.c2d(control.ss(A, B, C, 0), p.dt, "zoh")
        Ad, Bd = np.asarray(sysd.A), np.asarray(sysd.B)
        by_hand = np.block([[Ad - Bd @ K[:, :n], -Bd * K[0, n]], [-p.dt * C, np.ones((1, 1))]])
        ours = sampled_closed_loop(p, design_lqi(p))
        scale = np.abs(by_hand).max()
        np.testing.assert_allclose(ours, by_hand, rtol=1e-6, atol=1e-9 * scale)
        np.testing.assert_allclose(
            np.sort_complex(np.linalg.eigvals(ours)),
            np.sort_complex(np.linalg.eigvals(by_hand)),
            atol=1e-7,
        )


def test_settling_times_are_the_simulators(drawn):
    _, checks, draw = drawn
    steps = round(checks.duration / 0.05)
    for d in draw.kept[:30]:
        tr = simulate(d.plant, LQIController(d.plant), np.ones((1, steps)))
        t = step_metrics(tr.t, tr.y, tr.u, tr.r[:, -1])["settling_time"][0]
        assert d.settling_time == pytest.approx(t, abs=1e-9)
        assert d.settling_time <= checks.settle_fraction * checks.duration


def _plant(A, B, C, Q=None, R=1.0) -> Plant:
    A, B, C = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (A, B, C))
    n = A.shape[0]
    Q = np.eye(n + 1) if Q is None else np.atleast_2d(np.asarray(Q, dtype=float))
    return Plant(
        name="hand", tag=0, description="", source="", dt=0.05, A=A, B=B, C=C, Q=Q,
        R=np.array([[R]]), states=tuple(Signal(f"x{i}", "-") for i in range(n)),
        input_signal=Signal("u", "-"), output_signal=Signal("y", "-"), x_op=np.zeros(n),
    )  # fmt: skip


@pytest.mark.parametrize(
    ("plant", "reason", "text"),
    [
        # G = s / ((s + 1)(s + 2)): a zero at s = 0
        (_plant([[0, 1], [-2, -3]], [[0], [1]], [[0, 1]]), "zero_at_origin", "zero at s = 0"),
        # an unstable mode the input cannot reach
        (_plant([[1, 0], [0, -1]], [[0], [1]], [[1, 1]]), "not_stabilisable", "stabilisable"),
        # 1/s with a weight that makes the loop faster than the sample
        (_plant([[0]], [[1]], [[1]], Q=np.diag([1e6, 1e6])), "sampled_unstable", "sampled"),
        # an unstable plant and a negative definite Q: no stabilising Riccati solution
        (_plant([[1]], [[1]], [[1]], Q=-100 * np.eye(2)), "design_failed", "Riccati"),
        # 1/(s + 1) driven to a pole at 14 rad/s: the sample resolves it, max_pole_dt 0.5 not
        (_plant([[-1]], [[1]], [[1]], Q=np.diag([200.0, 1.0])), "too_fast", "14.18 rad/s"),
    ],
)
def test_each_design_refusal_has_its_reason(plant, reason, text):
    with pytest.raises(Rejected) as info:
        check_design(plant, max_pole_dt=0.8 if reason != "too_fast" else 0.5)
    assert info.value.reason == reason and reason in REASONS and text in info.value.message


def test_no_bandwidth_between_an_unstable_pole_and_an_rhp_zero():
    # (3 - s) / (8 (s - 1)(s + 5)): w_c >= 2 x 1 and w_c <= 3 / 2 cannot both hold
    A, B, C = [[1.0, 0.0], [1.0, -5.0]], [[1.0], [0.0]], [[-0.125, 1.0]]
    sys = control.ss(A, B, C, 0)
    assert np.asarray(sys.zeros()).real.max() == pytest.approx(3.0)
    rule = BrysonRule(bandwidth=(0.5, 4.0), integral_ratio=(0.5, 1.0), margin=2.0)
    with pytest.raises(NoBandwidthError, match=r"between 2 x its unstable pole \(1\) and its RHP"):
        rule.band(*(np.array(m) for m in (A, B, C)))
    lo, hi = BrysonRule((0.5, 4.0), (0.5, 1.0), 1.0).band(*(np.array(m) for m in (A, B, C)))
    assert (lo, hi) == pytest.approx((1.0, 3.0))


def test_a_family_whose_loops_are_too_slow_is_refused_with_the_counts():
    family, checks = _family("families.generator.weights.bandwidth=[0.05,0.1]")
    with pytest.raises(ValueError, match=r"only 0 of 5 plants pass .* 'too_slow': [1-9]"):
        draw_family(family, 5, checks)
    slow = [d for d in (family.candidate(i) for i in range(8)) if d.plant is not None]
    gains = [design_lqi(c.plant) for c in slow]
    times = settling_times([c.plant for c in slow], gains, 200)
    assert (times > checks.settle_fraction * checks.duration).all()


def test_every_candidate_before_the_last_is_kept_or_refused_with_its_reason(drawn):
    _, _, draw = drawn
    counts = draw.counts()
    indices = sorted([d.candidate.index for d in draw.kept] + [r["index"] for r in draw.rejected])
    assert indices == list(range(counts["candidates"]))
    assert counts["kept"] == COUNT and [d.plant.tag for d in draw.kept] == list(range(COUNT))
    assert sum(counts[r] for r in REASONS) == len(draw.rejected)
    assert counts["no_bandwidth"] > 0 and counts["too_slow"] > 0  # both occur at the default
    for r in draw.rejected:
        assert r["reason"] in REASONS and r["message"] and set(r) >= {"gain", "poles", "zeros"}
    record = json.loads(json.dumps(draw.record()))  # JSON-ready
    assert set(record["plants"]) == {d.plant.name for d in draw.kept}


def test_same_seed_same_plants_bit_for_bit_distinct_seeds_distinct_plants(drawn):
    family, checks, draw = drawn
    again = draw_family(family, 60, checks, chunk=7)  # other chunks, fewer plants: a prefix
    for a, b in zip(draw.kept[:60], again.kept, strict=True):
        for m in ("A", "B", "C", "Q", "R"):
            assert getattr(a.plant, m).tobytes() == getattr(b.plant, m).tobytes()
    first = json.dumps(draw.record()["plants"], sort_keys=True)
    assert first == json.dumps(
        draw_family(family, COUNT, checks).record()["plants"], sort_keys=True
    )
    other = draw_family(dataclasses.replace(family, seed=2), 60, checks)

    def models(d):  # (A, B, C): an order-1 integrator's A = [[0]] in every draw
        return b"".join(getattr(d.plant, m).tobytes() for m in "ABC")

    assert not {models(d) for d in draw.kept} & {models(d) for d in other.kept}
    assert other.kept[0].plant.name == "default_s2_" + f"{other.kept[0].candidate.index:05d}"


def test_a_mimo_family_and_bad_ranges_are_refused_naming_the_key():
    with pytest.raises(ValueError, match=r"inputs=2, outputs=1: MIMO families are not supported"):
        read_families(_families("families.generator.inputs=2"))
    with pytest.raises(ValueError, match=r"families\.generator\.gain = \[10\.0, 1\.0\] must be"):
        read_families(_families("families.generator.gain=[10,1]"))
    with pytest.raises(ValueError, match=r"families\.generator\.classes must map some of"):
        read_families(_families("+families.generator.classes.chaotic=1.0"))
    with pytest.raises(ValueError, match=r"families\.count must be at least 1"):
        read_families(_families("families.count=0"))


def test_weights_count_inputs_and_outputs():
    w = Weights(bandwidth=1.0, integral_ratio=0.5, q_y=2.0, q_z=0.5)
    C = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 0.0]])  # two outputs: two integrators
    Q, R = w.matrices(np.ones((3, 2)), C)
    assert Q.shape == (5, 5) and R.shape == (2, 2)
    np.testing.assert_array_equal(Q[:3, :3], 2.0 * C.T @ C)
    np.testing.assert_array_equal(Q[3:, 3:], 0.5 * np.eye(2))
