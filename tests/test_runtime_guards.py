"""The runtime's input range: absurd or non-finite inputs and outputs are refused, and a
refused step changes nothing (issue 10, item 5).

The policy is "trained" in closed form: its normaliser is fitted on LQI demonstrations of two
plants and its linear head is the least-squares fit of the expert's controls, so it controls
them like LQI without a training run. Every refusal is checked against a twin runtime that
never saw the refused call: from then on both must give bit-identical controls.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from generalist_control.data.windows import build_windows, integral_of_error
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import INPUT_LIMIT, PolicyRuntime, RejectedStep
from generalist_control.model.policy import Policy, save_policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.plant import MAX_ORDER, pad_states
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import Run, simulate, simulate_many
from helpers import lqi_law_policy

PLANTS = ("cstr", "hydraulic_actuator")  # orders 2 and 3
T, K = 8, 3


def _demo_windows():
    """Integral windows of LQI step responses of both plants (4 amplitudes, 4 s each)."""
    parts = []
    for name in PLANTS:
        plant = load_plant(name)
        amps = np.array([-3.0, -1.0, 0.5, 2.0]) * plant.amplitude_scale
        tr = simulate(plant, LQIController(plant), np.repeat(amps[:, None], 80, axis=1))
        z = integral_of_error(tr.r, tr.y[:, :-1], plant.dt)
        tag, order = np.full(4, plant.tag), np.full(4, plant.order)
        parts.append(build_windows(pad_states(tr.x[:, :-1]), tr.r, tr.u, tag, order, T, K, z))
    return {
        k: np.concatenate([getattr(w, k) for w in parts])
        for k in ("state", "mask", "ref", "tag", "target")
    }


@pytest.fixture(scope="module")
def demo():
    return _demo_windows()


@pytest.fixture(scope="module")
def trained(demo) -> tuple[Policy, dict]:
    """An integrating policy: normaliser fitted on the demonstrations, its law LQI's."""
    tensors = {k: torch.from_numpy(v) for k, v in demo.items()}
    return lqi_law_policy(PLANTS, design_lqi, fit=tensors)


def _rms(demo, name: str) -> dict[str, np.ndarray]:
    """Training RMS per signal of plant ``name``, computed here from the windows."""
    sel = demo["tag"] == load_plant(name).tag
    m = demo["mask"][sel].astype(float)
    sx = np.sqrt(((demo["state"][sel] * m) ** 2).sum((0, 1)) / m.sum((0, 1)).clip(1))
    sx[m.sum((0, 1)) == 0] = 1.0  # padding: no data, scale one
    return {
        "x": sx,
        "r": np.sqrt(np.mean(demo["ref"][sel].astype(float) ** 2)),
        "u": np.sqrt(np.mean(demo["target"][sel].astype(float) ** 2)),
    }


def _snapshot(rt: PolicyRuntime):
    state, mask, ref, tag = rt.window()
    return [a.copy() for a in (state, ref, rt.z, rt._u_prev, rt.plan)]


def _assert_same(a, b):
    for u, v in zip(a, b, strict=True):
        np.testing.assert_array_equal(u, v)


NORMAL = [([0.2, -0.1], 1.0), ([0.4, 0.0], 1.0), ([0.5, 0.1], 1.5), ([0.3, 0.2], 1.5)] * 3


@pytest.fixture(scope="module", params=["torch", "onnx"])
def backend(request) -> str:
    return request.param


def test_the_issue_reproductions_are_refused_and_change_nothing(trained, backend):
    """After reset("cstr"), step([1e39, 0], 1) and step([1e30, 0], 1): a clear error."""
    policy, meta = trained
    rt, twin = PolicyRuntime(policy, meta, backend), PolicyRuntime(policy, meta, backend)
    rt.reset("cstr")
    twin.reset("cstr")
    for bad in ([1e39, 0.0], [1e30, 0.0]):  # on the very first step: the buffer is empty
        with pytest.raises(ValueError, match=r"plant 'cstr': state entry 0 = 1e\+(39|30) is"):
            rt.step(bad, 1.0)
    for k, (x, r) in enumerate(NORMAL):
        if k in (3, 7):  # and in the middle of a run
            before = _snapshot(rt)
            for value in (1e39, 1e30, -1e30):
                with pytest.raises(ValueError, match="outside the allowed range .*reset"):
                    rt.step([value, 0.0], 1.0)
            _assert_same(_snapshot(rt), before)
        assert rt.step(x, r) == twin.step(x, r)  # bit for bit
        np.testing.assert_array_equal(rt.z, twin.z)
        np.testing.assert_array_equal(rt.plan, twin.plan)
        assert np.isfinite(rt.z).all()


@pytest.mark.parametrize("where", ["x", "r", "y"])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_state_reference_or_output_is_refused(trained, where, value):
    policy, meta = trained
    rt, twin = PolicyRuntime(policy, meta), PolicyRuntime(policy, meta)
    rt.reset("hydraulic_actuator")
    twin.reset("hydraulic_actuator")
    x, r, y = [0.1, -0.2, 0.05], 1.0, 0.2
    for _ in range(3):
        assert rt.step(x, r, y) == twin.step(x, r, y)
    args = {"x": x, "r": r, "y": y, where: value}
    if where == "x":
        args["x"] = [0.1, value, 0.05]
    label = {"x": "state entry 1", "r": "reference r", "y": "measured output y"}[where]
    kind = {"x": "state", "r": "reference", "y": "output"}[where]
    before = _snapshot(rt)
    with pytest.raises(RejectedStep, match=rf"'hydraulic_actuator': {label} = .*{kind} contains"):
        rt.step(args["x"], args["r"], args["y"])
    _assert_same(_snapshot(rt), before)
    for _ in range(3):
        assert rt.step(x, r, y) == twin.step(x, r, y)


def test_a_network_that_outputs_nan_or_absurd_controls_is_refused(trained, demo):
    policy, meta = trained
    broken = copy.deepcopy(policy)
    with torch.no_grad():
        for p in broken.net.parameters():
            p.fill_(float("nan"))
    rt = PolicyRuntime(broken, meta)
    rt.reset("cstr")
    with pytest.raises(ValueError, match=r"plant 'cstr': control u\[k\+0\] = nan is not finite"):
        rt.step([0.1, 0.0], 1.0)
    assert rt.z.tolist() == [0.0] and rt.plan.shape == (0, K)
    # through the onnx backend: its run function replaced, then given back
    rt, twin = PolicyRuntime(policy, meta, "onnx"), PolicyRuntime(policy, meta, "onnx")
    for r in (rt, twin):
        r.reset(["cstr", "hydraulic_actuator"])
    x, ref = np.array([[0.1, 0.0, 0, 0], [0.2, 0.1, -0.1, 0]]), np.array([1.0, -1.0])
    np.testing.assert_array_equal(rt.step(x, ref), twin.step(x, ref))
    clean, limit = rt._run, INPUT_LIMIT * _rms(demo, "hydraulic_actuator")["u"]
    for bad, msg in ((np.nan, "= nan is not finite"), (2 * limit, "outside the allowed range")):

        def corrupt(*args, bad=bad):
            u = clean(*args)
            u[1, 2] = bad
            return u

        rt._run = corrupt
        before = _snapshot(rt)
        with pytest.raises(RejectedStep, match=rf"row 1 \(plant 'hydraulic_actuator'\): .*{msg}"):
            rt.step(x, ref)
        _assert_same(_snapshot(rt), before)
    rt._run = clean
    for _ in range(4):
        np.testing.assert_array_equal(rt.step(x, ref), twin.step(x, ref))


def test_the_range_is_input_limit_times_the_training_rms(trained, demo, tmp_path):
    """At the boundary computed here from the demonstrations: just inside passes."""
    policy, meta = trained
    rt = PolicyRuntime.load(save_policy(tmp_path / "p.ckpt", policy, meta), input_limit=5.0)
    assert rt.input_limit == 5.0
    rt._run = lambda state, mask, ref, tag: np.zeros((len(tag), K), np.float32)  # inputs only
    rms = _rms(demo, "cstr")
    rt.reset("cstr")
    for i in range(2):
        x = np.zeros(2)
        x[i] = 0.999 * 5.0 * rms["x"][i]
        rt.step(x, 0.0)
        x[i] = 1.001 * 5.0 * rms["x"][i]
        with pytest.raises(ValueError, match=rf"state entry {i} = .* <= {5 * rms['x'][i]:.4g} "):
            rt.step(x, 0.0)
    rt.step([0.0, 0.0], 0.999 * 5.0 * rms["r"])
    with pytest.raises(ValueError, match=rf"reference r = .* <= {5 * rms['r']:.4g} \(= 5 x"):
        rt.step([0.0, 0.0], 1.001 * 5.0 * rms["r"])
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="input_limit must be a positive number"):
            PolicyRuntime(policy, meta, input_limit=bad)
    for doc in (PolicyRuntime.__doc__, PolicyRuntime.step.__doc__):
        assert "input_limit" in doc and "training RMS" in doc


def test_a_batch_is_refused_whole_naming_its_bad_rows(trained):
    policy, meta = trained
    names = ["cstr", "hydraulic_actuator", "cstr"]
    rt, twin = PolicyRuntime(policy, meta), PolicyRuntime(policy, meta)
    rt.reset(names)
    twin.reset(names)
    x, r = np.array([[0.1, 0.0, 0, 0], [0.2, 0.1, -0.1, 0], [0.3, 0, 0, 0]]), np.ones(3)
    np.testing.assert_array_equal(rt.step(x, r), twin.step(x, r))
    bad = x.copy()
    bad[2, 1], bad[1, 3] = np.inf, 1e39  # row 1: absurd padding beyond order 3
    before = _snapshot(rt)
    with pytest.raises(RejectedStep) as err:
        rt.step(bad, r)
    assert err.value.rows == (1, 2)
    msg = str(err.value)
    assert "row 1 (plant 'hydraulic_actuator'): state entry 3 (padding" in msg
    assert "row 2 (plant 'cstr'): state entry 1 = inf" in msg and "row 0" not in msg
    _assert_same(_snapshot(rt), before)
    # small padding is accepted as before and never reaches the network
    padded = x.copy()
    padded[0, 2:] = [0.5, -0.25]
    np.testing.assert_array_equal(rt.step(padded, r), twin.step(x, r))
    # narrower batches (B, max order) are accepted too
    np.testing.assert_array_equal(rt.step(x[:, :3], r), twin.step(x, r))


def test_a_winding_up_integral_is_refused_before_it_leaves_its_range(trained, demo):
    policy, meta = trained
    rt = PolicyRuntime(policy, meta, input_limit=3.0)
    rt._run = lambda state, mask, ref, tag: np.zeros((len(tag), K), np.float32)
    rt.reset("cstr")
    rms = _rms(demo, "cstr")
    z_max = 3.0 * rms["x"][MAX_ORDER]
    r, y = 2.5 * rms["r"], -2.5 * rms["r"]
    with pytest.raises(
        ValueError, match="error integral z after this sample .*set_actuator_limits"
    ):
        for _ in range(1000):
            z = rt.z.copy()
            rt.step([0.0, 0.0], r, y)
    np.testing.assert_array_equal(rt.z, z)  # the refused step left it
    assert abs(z[0]) <= z_max < abs(z[0]) + 0.05 * (r - y)
    rt.step([0.0, 0.0], r, r)  # a step that does not integrate goes on
    np.testing.assert_array_equal(rt.z, z)


def test_the_adapter_drops_runs_the_runtime_refuses_and_keeps_the_others(trained):
    """A run started far outside the range is reported diverged; the others are unchanged."""
    policy, meta = trained
    plants = [load_plant(n) for n in PLANTS]
    r = [np.full((2, 40), 1.0), np.full((1, 40), -1.0)]
    x0 = np.array([[0.0, 0.0], [1e7, 0.0]])  # cstr's run 1: outside (and diverging)
    adapter = RuntimeAdapter(PolicyRuntime(policy, meta))
    got = simulate_many([Run(plants[0], r[0], x0), Run(plants[1], r[1])], adapter)
    assert list(adapter.refused) == [1] and "row 1 (plant 'cstr')" in adapter.refused[1]
    assert got[0].diverged.tolist() == [False, True] and np.isnan(got[0].u[1]).all()
    alone = simulate_many(
        [Run(plants[0], r[0][:1], x0[:1]), Run(plants[1], r[1])],
        RuntimeAdapter(PolicyRuntime(policy, meta)),
    )
    np.testing.assert_array_equal(got[0].u[0], alone[0].u[0])
    np.testing.assert_array_equal(got[1].u, alone[1].u)
    assert not alone[0].diverged.any() and not alone[1].diverged.any()


# --- property: every call gives finite controls or a clear error, and changes nothing then --

SPECIAL = [np.nan, np.inf, -np.inf, 1e39, -1e39, 1e30, -1e300, 3e3, -2e3, 1e6]
value = st.one_of(st.floats(-4, 4), st.sampled_from(SPECIAL))
#: network outputs far beyond any plant's control range (always refused)
ABSURD = [np.nan, np.inf, -np.inf, 1e39, -1e30, 1e6]


@st.composite
def _call(draw, names: list[str], single: bool):
    """One step's (x, r, y): mostly normal values, sometimes one entry replaced."""
    B = len(names)
    width = load_plant(names[0]).order if single else MAX_ORDER
    x = np.zeros((B, width))
    for i, name in enumerate(names):
        n = load_plant(name).order
        x[i, :n] = draw(st.lists(st.floats(-3, 3), min_size=n, max_size=n))
    r = np.array(draw(st.lists(st.floats(-3, 3), min_size=B, max_size=B)))
    y = (
        None
        if draw(st.booleans())
        else np.array(draw(st.lists(st.floats(-3, 3), min_size=B, max_size=B)))
    )
    what = draw(st.sampled_from(["none"] * 4 + ["x", "r", "y", "u", "shape"]))
    if what == "x":
        x[draw(st.integers(0, B - 1)), draw(st.integers(0, width - 1))] = draw(value)
    elif what == "r":
        r[draw(st.integers(0, B - 1))] = draw(value)
    elif what == "y":
        y = np.zeros(B) if y is None else y
        y[draw(st.integers(0, B - 1))] = draw(value)
    elif what == "shape":
        x = x[:, :-1] if draw(st.booleans()) else np.vstack([x, x[:1]])
    bad_u = draw(st.sampled_from(ABSURD)) if what == "u" else None
    if single:
        return x[0], float(r[0]), None if y is None else float(y[0]), bad_u
    return x, r, y, bad_u


@st.composite
def _scenario(draw):
    names = draw(st.lists(st.sampled_from(PLANTS), min_size=1, max_size=4))
    single = len(names) == 1 and draw(st.booleans())
    calls = draw(st.lists(_call(names, single), min_size=1, max_size=10))
    return (names[0] if single else names), calls


@pytest.fixture(scope="module")
def pair(trained):
    """The runtime under test (its network output can be corrupted) and its twin."""
    policy, meta = trained
    rt, twin = PolicyRuntime(policy, meta), PolicyRuntime(policy, meta)
    clean, corrupt = rt._run, {"value": None}

    def run(*args):
        u = clean(*args)
        if corrupt["value"] is not None:
            with np.errstate(over="ignore"):  # 1e39 is inf in float32, as intended
                u[-1, -1] = corrupt["value"]
        return u

    rt._run = run
    return rt, twin, corrupt


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenario=_scenario())
def test_fuzz_finite_controls_or_a_clear_error_and_a_refused_call_changes_nothing(pair, scenario):
    rt, twin, corrupt = pair
    system, calls = scenario
    rt.reset(system)
    twin.reset(system)
    B = 1 if isinstance(system, str) else len(system)
    for x, r, y, bad_u in calls:
        corrupt["value"] = bad_u
        try:
            u = rt.step(x, r, y)
        except (ValueError, RuntimeError) as err:
            assert str(err).strip()
            continue
        assert bad_u is None  # an absurd network output is never returned
        expected = twin.step(x, r, y)  # the twin sees only the accepted calls
        if isinstance(system, str):
            assert isinstance(u, float) and np.isfinite(u) and u == expected
        else:
            assert u.shape == (B,) and np.isfinite(u).all()
            np.testing.assert_array_equal(u, expected)
        np.testing.assert_array_equal(rt.plan, twin.plan)
        np.testing.assert_array_equal(rt.z, twin.z)
        assert np.isfinite(rt.plan).all() and np.isfinite(rt.z).all()
