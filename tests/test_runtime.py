"""The policy runtime: stepping equals the batch forward, exports, bad input, safe loading."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from generalist_control.catalog import load_plant
from generalist_control.lqi import LQIController
from generalist_control.plants import MAX_ORDER
from generalist_control.policy import Policy, load_policy, save_policy
from generalist_control.runtime import PolicyRuntime, resolve
from generalist_control.simulate import simulate
from generalist_control.windows import build_windows, pad_states

PLANTS = ("cstr", "hydraulic_actuator")  # orders 2 and 3


def _meta() -> dict:
    return {
        "tags": {p: load_plant(p).tag for p in PLANTS},
        "orders": {p: load_plant(p).order for p in PLANTS},
        "dt": 0.05,
        "history": 8,
        "horizon": 3,
    }


@pytest.fixture(scope="module", params=[0, 1], ids=["paper", "ours"])
def policy(request) -> Policy:
    """A random policy with non-trivial normaliser scales (no training needed here).

    ``ours``: window scaling and the linear head on, the head's weights made non-zero.
    """
    torch.manual_seed(0)
    on = request.param
    pol = Policy({"hidden": 16, "experts": 3, "window_scale": on, "linear_head": on}).eval()
    g = torch.Generator().manual_seed(1)
    if on:
        with torch.no_grad():
            pol.net.linear.weight.normal_(0.0, 0.1, generator=g)
    pol.normaliser.state_scale.uniform_(0.5, 3.0, generator=g)
    pol.normaliser.ref_scale.uniform_(0.5, 3.0, generator=g)
    pol.normaliser.control_scale.uniform_(0.5, 3.0, generator=g)
    return pol


def _lqi_trajectory(name: str, amplitude: float, steps: int = 60):
    plant = load_plant(name)
    r = np.full((1, steps), amplitude)
    tr = simulate(plant, LQIController(plant), r)
    return plant, tr


def test_stepping_equals_the_batch_forward_on_built_windows(policy):
    """Each step's plan equals the network on the window the one window builder makes."""
    runtime = PolicyRuntime(policy, _meta())
    for name, amp in (("cstr", 1.5), ("hydraulic_actuator", -3.0)):
        plant, tr = _lqi_trajectory(name, amp)
        x = pad_states(tr.x[:, :-1])
        w = build_windows(x, tr.r, tr.u, np.array([plant.tag]), np.array([plant.order]), 8, 1)
        expected, _ = policy.predict_windows(w)
        runtime.reset(name)
        plans = []
        for k in range(tr.r.shape[1]):
            u = runtime.step(tr.x[0, k], tr.r[0, k])
            assert u == pytest.approx(float(runtime.plan[0, 0]))
            plans.append(runtime.plan[0])
        np.testing.assert_allclose(np.array(plans), expected, rtol=1e-5, atol=1e-6)


def test_batched_stepping_equals_single_runs(policy):
    runtime = PolicyRuntime(policy, _meta())
    runs = [_lqi_trajectory("cstr", 2.0), _lqi_trajectory("hydraulic_actuator", 0.5)]
    singles = []
    for plant, tr in runs:
        runtime.reset(plant.name)
        singles.append([runtime.step(tr.x[0, k], tr.r[0, k]) for k in range(20)])
    runtime.reset([p.name for p, _ in runs])
    batched = []
    for k in range(20):
        x = np.stack([pad_states(tr.x[:, k : k + 1])[0, 0] for _, tr in runs])
        r = np.array([tr.r[0, k] for _, tr in runs])
        batched.append(runtime.step(x, r))
    np.testing.assert_allclose(np.array(batched).T, np.array(singles), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("backend", ["torchscript", "onnx"])
def test_exports_equal_pytorch_within_1e_5(policy, backend):
    rng = np.random.default_rng(0)
    reference = PolicyRuntime(policy, _meta(), backend="torch")
    exported = PolicyRuntime(policy, _meta(), backend=backend)
    names = ["cstr", "hydraulic_actuator", "cstr", "hydraulic_actuator", "cstr"]
    for rt in (reference, exported):
        rt.reset(names)
    for _ in range(12):  # batch 5 (the exports were traced at batch 2: dynamic batch axis)
        x = rng.normal(scale=2.0, size=(5, MAX_ORDER))
        r = rng.normal(scale=5.0, size=5)
        a, b = reference.step(x, r), exported.step(x, r)
        np.testing.assert_allclose(b, a, atol=1e-5, rtol=1e-5)
        np.testing.assert_allclose(exported.plan, reference.plan, atol=1e-5, rtol=1e-5)


def test_bad_input_gets_clear_errors(policy):
    runtime = PolicyRuntime(policy, _meta())
    with pytest.raises(RuntimeError, match="reset"):
        runtime.step([0.0, 0.0], 1.0)
    with pytest.raises(KeyError, match="unknown plant 'pendulum'.*cstr, hydraulic_actuator"):
        runtime.reset("pendulum")
    runtime.reset("hydraulic_actuator")
    with pytest.raises(ValueError, match=r"shape \(2,\); plant 'hydraulic_actuator' has 3"):
        runtime.step([0.0, 0.0], 1.0)
    with pytest.raises(ValueError, match="NaN or inf"):
        runtime.step([0.0, np.nan, 0.0], 1.0)
    with pytest.raises(ValueError, match="NaN or inf"):
        runtime.step([0.0, 0.0, 0.0], np.inf)
    runtime.reset(["cstr", "cstr"])
    with pytest.raises(ValueError, match="expected \\(2, 4\\)"):
        runtime.step(np.zeros((3, 4)), np.zeros(3))
    with pytest.raises(ValueError, match="unknown backend 'tensorrt'"):
        PolicyRuntime(policy, _meta(), backend="tensorrt")
    with pytest.raises(FileNotFoundError, match="python train.py"):
        resolve("no/such/policy.ckpt")


class _Evil:
    def __reduce__(self):
        return (print, ("arbitrary code ran",))


def test_loading_is_weights_only(policy, tmp_path):
    path = save_policy(tmp_path / "policy.ckpt", policy, _meta())
    loaded = PolicyRuntime.load(path)
    loaded.reset("cstr")
    ref = PolicyRuntime(policy, _meta())
    ref.reset("cstr")
    assert loaded.step([0.3, -0.1], 1.0) == pytest.approx(ref.step([0.3, -0.1], 1.0), abs=1e-7)
    evil = tmp_path / "evil.ckpt"
    blob = torch.load(path, weights_only=True)
    blob["meta"]["payload"] = _Evil()
    with evil.open("wb") as fh:
        torch.save(blob, fh, pickle_module=pickle)
    with pytest.raises(pickle.UnpicklingError):
        load_policy(evil)
