"""One plant stepped alone (issue 38): the per-sample path and the plant's own ONNX graph.

``PolicyRuntime.step`` for a runtime reset to one plant takes a path on Python numbers and,
with ONNX, a graph made for that plant at batch 1: written from the weights (the paper's
network and the default, deploy/onnx_plant.py) or the exported graph shrunk (the others).
Both must give exactly what the general path gives (``specialise=False``): the same
controls, plans, error integrals and windows, bit for bit, on every network variant. The
graph rewrites behind the shrunk graph are checked one by one in
tests/test_runtime_onnx_graph.py.
"""

from __future__ import annotations

import warnings

import numpy as np
import onnx
import pytest
import torch
from onnx import helper

from generalist_control.data.windows import HistoryBuffer
from generalist_control.deploy import export, onnx_backend
from generalist_control.deploy.export import backend, onnx_bytes
from generalist_control.deploy.onnx_graph import Graph
from generalist_control.deploy.onnx_plant import plant_graph
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
    "skip8": {"window_scale": True, "channels": ["integral"], "skip": "linear",
              "skip_samples": 8},
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
        if pol.net.skip is not None:
            pol.net.skip.gains.weight.normal_(0.0, 0.05, generator=g)
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


WRITTEN = ("paper", "default")  # the variants whose plant graph is written from the weights


def test_the_plant_graph_is_smaller_and_computes_what_the_general_session_does(policy, request):
    pol, _ = policy
    variant = request.node.callspec.params["policy"]
    run = backend(pol, "onnx")
    rng = np.random.default_rng(0)
    one = onnx.load_from_string(onnx_bytes(pol, batch=1))
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
        shrunk = onnx.load_from_string(onnx_backend.shrink(one, fixed, ["controls"]))
        assert len(shrunk.graph.node) < 0.8 * len(one.graph.node)
        written = plant_graph(pol, plant.tag, buffer.mask)
        assert (written is not None) == (variant in WRITTEN)
        if written is not None:  # fewer nodes still, and the one the runtime steps through
            assert len(onnx.load_from_string(written).graph.node) < len(shrunk.graph.node)
            width = buffer.mask.shape[2]
            assert [i.shape for i in single._sess.get_inputs()] == [[8, width], [8, 1]]


def _off(graph: bytes | None) -> bytes | None:
    """``graph`` with every control 1 % off."""
    if graph is None:
        return None
    g = Graph.from_model(onnx.load_from_string(graph))
    g.consts["off"] = np.array(1.01, np.float32)
    g.nodes[-1].output[0] = "controls/right"
    g.nodes.append(helper.make_node("Mul", ["controls/right", "off"], ["controls"]))
    return g.to_model().SerializeToString()


@pytest.mark.parametrize("wrong", ["written", "both"])
def test_a_plant_graph_that_disagrees_is_not_used(policy, monkeypatch, wrong):
    """The check at reset: a wrong graph gives way to the next, at last the general session.

    A wrong written graph to the shrunk one, silently; a wrong shrunk one too (or the only
    one) to the general session, with a warning.
    """
    pol, meta = policy
    monkeypatch.setattr(export, "plant_graph", lambda *args: _off(plant_graph(*args)))
    real, shrunk = onnx_backend.shrink, []
    monkeypatch.setattr(onnx_backend, "shrink", lambda *a: shrunk.append(1) or (
        _off(real(*a)) if wrong == "both" else real(*a)))  # fmt: skip
    rt = PolicyRuntime(pol, meta, backend="onnx")
    if wrong == "both":
        with pytest.warns(RuntimeWarning, match="differs from the general session by 0.01"):
            rt.reset("cstr")
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            rt.reset("cstr")
    assert shrunk == [1]
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
        extras = np.array([r]), np.array([z]), np.array([u])
        if k in (4, 7):  # the general path steps the same buffer now and then
            sa, _, ra = a.stage(padded, *extras)
        else:
            sa, ra = a.stage_one(x, r, z, u)
        sb, _, rb = b.stage(padded, *extras)
        np.testing.assert_array_equal(sa, sb)
        np.testing.assert_array_equal(ra, rb)
        if k % 3 != 2:  # some staged windows are dropped, as a refused step's are
            a.commit()
            b.commit()
        if k == 8:  # a batch's rows selected: the buffer's arrays are new ones
            a.select(np.array([0]))
            b.select(np.array([0]))
