"""The runtime's weak answers of issues 36 and 51: limits, inputs, plants, threads.

* ``set_actuator_limits`` with a limit of zero or below, or NaN, is refused (it froze the
  error integral or made the command NaN);
* a complex, bool or string state, reference, output or applied control is refused, naming
  the input (NumPy made a float of it), and the runtime is left as it was;
* ``reset`` given no name (None, a number) says what it takes and which plants it knows;
* a second thread entering a runtime another thread is inside is refused (two threads
  stepping one runtime raised "nothing staged" now and then);
* building the ONNX backend leaves nothing in the temporary directory (each
  load left a ``tmp*/policy.*`` folder behind).
"""

from __future__ import annotations

import tempfile
import threading

import numpy as np
import pytest
import torch

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import PlantConfigError
from helpers import net_config, policy_meta

PLANTS = ("cstr", "hydraulic_actuator")  # orders 2 and 3


@pytest.fixture(scope="module")
def policy() -> tuple[Policy, dict]:
    """A small integrating policy (random weights; the checks do not depend on them)."""
    torch.manual_seed(0)
    config = net_config(hidden=8, experts=2, window_scale=True, channels=["integral"],
                        skip="linear")  # fmt: skip
    return Policy(config).eval(), policy_meta(PLANTS, 8, 3)


def _state(rt: PolicyRuntime) -> list[np.ndarray]:
    state, _, ref, _ = rt.window()
    return [a.copy() for a in (state, ref, rt.z, rt._u_prev, rt.plan)]


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"u_limit": 0.0}, "u_limit"),
        ({"u_limit": -0.5}, "u_limit"),
        ({"u_limit": float("nan")}, "u_limit"),
        ({"u_limit": "a lot"}, "u_limit"),
        ({"rate_limit": 0.0}, "rate_limit"),
        ({"u_limit": 1.0, "rate_limit": float("nan")}, "rate_limit"),
    ],
)
def test_a_limit_that_is_not_a_positive_number_is_refused(policy, kwargs, name):
    rt = PolicyRuntime(*policy)
    rt.set_actuator_limits(u_limit=2.0)
    before = rt.limits
    with pytest.raises(ValueError, match=rf"^{name} must be a positive number .*got"):
        rt.set_actuator_limits(**kwargs)
    assert rt.limits is before  # the limits known before are kept


def test_positive_limits_and_none_are_taken(policy):
    rt = PolicyRuntime(*policy)
    rt.set_actuator_limits(u_limit=0.25, rate_limit=np.float32(3.0))
    assert rt.limits is not None
    assert (rt.limits.u_limit, rt.limits.rate_limit) == (0.25, 3.0)
    rt.set_actuator_limits(u_limit=np.inf)  # no limit in effect, but a valid one
    rt.set_actuator_limits()
    assert rt.limits is None


@pytest.mark.parametrize("backend", ["torch", "onnx"])
@pytest.mark.parametrize("where", ["x", "r", "y"])
def test_a_complex_input_to_one_plant_is_refused_and_changes_nothing(policy, backend, where):
    rt = PolicyRuntime(*policy, backend=backend)
    rt.reset("hydraulic_actuator")
    x, r, y = np.array([0.1, -0.2, 0.05]), 1.0, 0.2
    rt.step(x, r, y)
    before = _state(rt)
    bad = {"x": x + 0.5j, "r": np.complex128(1.0 + 1e-3j), "y": np.array([0.2 + 1j])}[where]
    args = {"x": x, "r": r, "y": y, where: bad}
    label = {"x": "state x", "r": "reference r", "y": "measured output y"}[where]
    with pytest.raises(TypeError, match=rf"{label} is complex \(complex128\).*real part"):
        rt.step(args["x"], args["r"], args["y"])
    for a, b in zip(_state(rt), before, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_complex_batch_or_applied_control_is_refused(policy):
    rt = PolicyRuntime(*policy)
    rt.reset(["cstr", "hydraulic_actuator"])
    x = np.array([[0.1, 0.0, 0, 0], [0.2, 0.1, -0.1, 0]])
    with pytest.raises(TypeError, match="state x is complex"):
        rt.step(x.astype(complex), np.ones(2))
    with pytest.raises(TypeError, match="reference r is complex"):
        rt.step(x, np.ones(2, complex))
    rt.step(x, np.ones(2))
    with pytest.raises(TypeError, match="applied control u is complex"):
        rt.record_applied(np.array([0.1, 0.2j]))
    # a complex dtype holding real values is refused too: the caller says which part to use
    with pytest.raises(TypeError, match="state x is complex"):
        rt.step(x + 0j, np.ones(2))


@pytest.mark.parametrize("backend", ["onnx"])
def test_building_a_backend_leaves_nothing_in_the_temporary_directory(
    policy, backend, tmp_path, monkeypatch
):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    rt = PolicyRuntime(*policy, backend=backend)
    rt.reset("cstr")  # one plant: the ONNX backend builds its batch-1 graph too
    rt.step([0.1, 0.0], 1.0)
    rt.reset(list(PLANTS))
    rt.step(np.zeros((2, 4)), np.ones(2))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("backend", ["torch", "onnx"])
@pytest.mark.parametrize(
    ("where", "bad", "says"),
    [
        ("r", "1.0", r"reference r is a string \('1.0'\).*float\(\.\.\.\)"),
        ("x", [True, False], r"state x is a bool \(\[True, False\]\); .*real numbers only"),
        ("x", np.array([0.1, 0.2], object), r"state x is of type object"),
        ("y", "0.2", r"measured output y is a string"),
        ("r", True, r"reference r is a bool"),
    ],
)
def test_a_string_or_bool_input_is_refused_and_changes_nothing(policy, backend, where, bad, says):
    rt = PolicyRuntime(*policy, backend=backend)
    rt.reset("cstr")
    x, r, y = np.array([0.1, -0.2]), 1.0, 0.2
    rt.step(x, r, y)
    before = _state(rt)
    args = {"x": x, "r": r, "y": y, where: bad}
    with pytest.raises(TypeError, match=says):
        rt.step(args["x"], args["r"], args["y"])
    for a, b in zip(_state(rt), before, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_bool_batch_or_applied_control_is_refused(policy):
    rt = PolicyRuntime(*policy)
    rt.reset(["cstr", "hydraulic_actuator"])
    x = np.array([[0.1, 0.0, 0, 0], [0.2, 0.1, -0.1, 0]])
    with pytest.raises(TypeError, match="state x is a bool"):
        rt.step(x > 0, np.ones(2))
    with pytest.raises(TypeError, match="reference r is a string"):
        rt.step(x, np.array(["1", "1"]))
    rt.step(x, np.ones(2))
    with pytest.raises(TypeError, match="applied control u is a bool"):
        rt.record_applied(np.array([True, False]))


@pytest.mark.parametrize("bad", [None, 25, 2.5, [1, 2], {"cstr": 1}, b"cstr"])
def test_reset_without_plants_says_what_it_takes_and_changes_nothing(policy, bad):
    rt = PolicyRuntime(*policy)
    rt.reset("cstr")
    rt.step([0.1, 0.0], 1.0)
    before = _state(rt)
    if isinstance(bad, dict):  # a dict is a plant's model: this one lacks its keys
        with pytest.raises(PlantConfigError, match=r"needs the keys \['A', 'B', 'C', 'dt'"):
            rt.reset(bad)
    else:
        with pytest.raises(TypeError) as err:
            rt.reset(bad)
        assert str(err.value).startswith("reset takes a plant (a name, a plant YAML's path")
        assert str(err.value).endswith("This policy knows: cstr, hydraulic_actuator")
    for a, b in zip(_state(rt), before, strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="at least one plant; known: cstr, hydraulic"):
        rt.reset([])
    rt.step([0.1, 0.0], 1.0)  # still the run on cstr


@pytest.mark.parametrize("backend", ["torch", "onnx"])
def test_a_second_thread_entering_a_runtime_in_use_is_refused(policy, backend):
    """Thread A is held inside the network; the main thread's calls meanwhile are refused."""
    rt, twin = PolicyRuntime(*policy, backend=backend), PolicyRuntime(*policy, backend=backend)
    inside, leave = threading.Event(), threading.Event()
    clean = rt._run

    def held(*args):
        inside.set()
        assert leave.wait(10)
        return clean(*args)

    rt.reset("cstr")
    twin.reset("cstr")
    rt._run = held
    result: list[float] = []
    a = threading.Thread(target=lambda: result.append(rt.step([0.1, 0.0], 1.0)))
    a.start()
    assert inside.wait(10)
    calls = [lambda: rt.step([0.3, 0.0], 1.0), lambda: rt.reset("hydraulic_actuator"),
             lambda: rt.record_applied(0.5), lambda: rt.set_actuator_limits(1.0),
             lambda: rt.select([0])]  # fmt: skip
    for call in calls:
        with pytest.raises(RuntimeError, match=r"another thread is inside this runtime.*own"):
            call()
    leave.set()
    a.join(10)
    rt._run = clean
    assert result == [twin.step([0.1, 0.0], 1.0)]  # A's step, and nothing of the refused
    assert rt.step([0.2, 0.1], -1.0) == twin.step([0.2, 0.1], -1.0)
    assert rt.limits is None


def test_two_threads_stepping_one_runtime_get_a_clear_error_or_a_control(policy):
    rt = PolicyRuntime(*policy, backend="onnx")
    rt.reset("cstr")
    errors: list[str] = []

    def loop() -> None:
        for _ in range(400):
            try:
                rt.step([0.1, 0.0], 0.5)
            except RuntimeError as err:
                errors.append(str(err))

    threads = [threading.Thread(target=loop) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert all("another thread is inside this runtime" in e for e in errors), errors[:3]
