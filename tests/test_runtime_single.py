"""One plant stepped alone (issue 38): the per-sample path and the plant's own ONNX graph.

``PolicyRuntime.step`` for a runtime reset to one plant takes a path on Python numbers and,
with ONNX, a graph made for that plant at batch 1. Both must give exactly what the general
path gives (``specialise=False``): the same controls, plans, error integrals and windows,
bit for bit, on every network variant. The graph rewrites behind the plant's graph are
checked one by one in tests/test_runtime_onnx_graph.py.
"""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch
from onnx import helper

from generalist_control.data.windows import HistoryBuffer
from generalist_control.deploy import onnx_backend
from generalist_control.deploy.export import backend, onnx_bytes
from generalist_control.deploy.onnx_graph import Graph
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import simulate
from helpers import net_config, policy_meta

PLANTS = ("cstr", "hydraulic_actuator", "two_mass_spring")  # orders 2, 3 and 4

VARIANTS = {
    "paper": {},
    "default": {"window_scale": True, "channels": ["integral"], "skip": "linear"},
    "table": {"window_scale": True, "channels": ["integral"], "table": 8},
    "tag-free": {"window_scale": True, "channels": ["integral", "previous_control"],
                 "skip": "context", "plant": "inferred", "models": None},
}  # fmt: skip


@pytest.fixture(scope="module", params=list(VARIANTS))
def policy(request) -> tuple[Policy, dict]:
    """A random policy of each variant, its linear paths and scales non-trivial."""
    torch.manual_seed(0)
    pol = Policy(net_config(hidden=16, experts=3, **VARIANTS[request.param])).eval()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        linear = [pol.net.table.weight if pol.net.table is not None else None,
                  pol.net.skip.gains if pol.net.skip is not None else None]  # fmt: skip
        for path in linear:
            if path is not None:
                path.weight.normal_(0.0, 0.05, generator=g)
        for expert in pol.net.experts:  # LayerNorm weights of their own
            for layer in expert:
                if isinstance(layer, torch.nn.LayerNorm):
                    layer.weight.uniform_(0.5, 1.5, generator=g)
                    layer.bias.normal_(0.0, 0.1, generator=g)
    pol.normaliser.state_scale.uniform_(0.5, 3.0, generator=g)
    pol.normaliser.ref_scale.uniform_(0.5, 3.0, generator=g)
    pol.normaliser.control_scale.uniform_(0.5, 3.0, generator=g)
    if request.param == "tag-free":  # the random net's feedback on its own control, bounded
        pol.normaliser.state_scale[:, -1] = 10.0
    return pol, policy_meta(PLANTS)


def _run(rt: PolicyRuntime, name: str, amplitude: float, measured: bool) -> list:
    """Step ``rt`` along an LQI step response of ``name``; everything the runtime shows."""
    plant = load_plant(name)
    tr = simulate(plant, LQIController(plant), np.full((1, 40), amplitude))
    rt.reset(name)
    seen = []
    for k in range(40):
        y = tr.y[0, k] if measured else None
        u = rt.step(tr.x[0, k], tr.r[0, k], y)
        state, _, ref, _ = rt.window()
        seen.append([u, rt.plan.copy(), rt.z.copy(), rt._u_prev.copy(), state.copy(), ref.copy()])
    return seen


@pytest.mark.parametrize("backend_name", ["torch", "onnx"])
@pytest.mark.parametrize("measured", [False, True])
def test_one_plant_steps_exactly_as_the_general_path(policy, backend_name, measured):
    fast = PolicyRuntime(*policy, backend=backend_name)
    general = PolicyRuntime(*policy, backend=backend_name, specialise=False)
    for name, amplitude in (("cstr", 1.5), ("hydraulic_actuator", -3.0), ("two_mass_spring", 2)):
        a = _run(fast, name, amplitude, measured)
        b = _run(general, name, amplitude, measured)
        for got, want in zip(a, b, strict=True):
            assert isinstance(got[0], float) and got[0] == want[0]
            for x, y in zip(got[1:], want[1:], strict=True):
                np.testing.assert_array_equal(x, y)


def test_the_plant_graph_is_smaller_and_computes_what_the_general_session_does(policy):
    pol, _ = policy
    run = backend(pol, "onnx")
    rng = np.random.default_rng(0)
    for name in PLANTS:
        plant = load_plant(name)
        buffer = HistoryBuffer(np.array([plant.order]), 8, "integral" in pol.channels,
                               "previous_control" in pol.channels)  # fmt: skip
        single = run.single(plant.tag, buffer.mask)
        tag = np.array([plant.tag])
        for scale in (1e-2, 1.0, 30.0):
            state = (rng.normal(size=buffer.mask.shape) * scale).astype(np.float32) * buffer.mask
            ref = (rng.normal(size=(1, 8)) * scale).astype(np.float32)
            np.testing.assert_array_equal(single(state, ref), run(state, buffer.mask, ref, tag))
        fixed = {"tag": tag, "mask": buffer.mask}
        one = onnx.load_from_string(onnx_bytes(pol, batch=1))
        shrunk = onnx.load_from_string(onnx_backend.shrink(one, fixed, ["controls"]))
        assert len(shrunk.graph.node) < 0.8 * len(one.graph.node)


def test_a_plant_graph_that_disagrees_is_not_used(policy, monkeypatch):
    """The check at reset: a wrong shrunk graph gives way to the plain batch-1 graph."""
    pol, meta = policy
    real = onnx_backend.shrink

    def wrong(model, fixed, keep):  # every control 1 % off
        g = Graph.from_model(onnx.load_from_string(real(model, fixed, keep)))
        g.consts["off"] = np.array(1.01, np.float32)
        g.nodes[-1].output[0] = "controls/right"
        g.nodes.append(helper.make_node("Mul", ["controls/right", "off"], ["controls"]))
        return g.to_model().SerializeToString()

    monkeypatch.setattr(onnx_backend, "shrink", wrong)
    rt = PolicyRuntime(pol, meta, backend="onnx")
    with pytest.warns(RuntimeWarning, match="differs from the general session by 0.01"):
        rt.reset("cstr")
    general = PolicyRuntime(pol, meta, backend="onnx", specialise=False)
    general.reset("cstr")
    for k in range(5):
        assert rt.step([0.1 * k, 0.0], 1.0) == general.step([0.1 * k, 0.0], 1.0)


def test_a_replaced_network_is_what_one_plant_steps_through(policy):
    """The runtime's run function, swapped (as the guard tests corrupt it), is used."""
    rt = PolicyRuntime(*policy, backend="onnx")
    rt.reset("cstr")
    rt._run = lambda state, mask, ref, tag: np.full((len(tag), 3), 0.125, np.float32)
    assert rt.step([0.1, 0.0], 1.0) == 0.125


@pytest.mark.parametrize(("integral", "controls"), [(False, False), (True, False), (True, True)])
def test_stage_one_writes_the_window_stage_writes(integral, controls):
    rng = np.random.default_rng(3)
    order = np.array([3])
    a, b = (HistoryBuffer(order, 6, integral, controls) for _ in range(2))
    for k in range(10):
        x, r, z, u = rng.normal(size=3), float(rng.normal()), float(rng.normal()), rng.normal()
        padded = np.zeros((1, 4))
        padded[0, :3] = x
        sa, ra = a.stage_one(x, r, z, u)
        sb, _, rb = b.stage(padded, np.array([r]), np.array([z]), np.array([u]))
        np.testing.assert_array_equal(sa, sb)
        np.testing.assert_array_equal(ra, rb)
        if k % 3 != 2:  # some staged windows are dropped, as a refused step's are
            a.commit()
            b.commit()
