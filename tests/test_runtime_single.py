"""One plant stepped alone: the per-sample path and the plant's own batch-1 ONNX graph.

``PolicyRuntime.step`` for a runtime reset to one plant by name takes a path on Python
numbers and, with ONNX, the policy's batch-1 export with the plant's tag and mask made
constants and shrunk. Both must give exactly what the general path gives (the same plant as
a batch of one): the same controls, plans, error integrals and windows, bit for bit, on every
network variant. The graph rewrites are checked one by one in
tests/test_runtime_onnx_graph.py.
"""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch

from generalist_control.data.windows import HistoryBuffer
from generalist_control.deploy.export import backend, onnx_bytes, plant_model
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.plant import MAX_ORDER
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import simulate
from helpers import net_config, policy_meta

PLANTS = ("cstr", "hydraulic_actuator", "two_mass_spring")  # orders 2, 3 and 4

VARIANTS = {
    "paper": {},
    "default": {"window_scale": True, "channels": ["integral"], "skip": "linear"},
    "skip8": {"window_scale": True, "channels": ["integral"], "skip": "linear",
              "skip_samples": 8},
    "short law": {"window_scale": True, "channels": ["integral"], "skip": "linear",
                  "law_history": 4, "stride": 3},
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


def _run(rt: PolicyRuntime, name: str, amplitude: float, measured: bool, batch: bool) -> list:
    """Step ``rt`` along an LQI step response of ``name``; everything the runtime shows.

    ``batch``: as a batch of one (padded states, arrays), the general path.
    """
    plant = load_plant(name)
    tr = simulate(plant, LQIController(plant), np.full((1, 40), amplitude))
    rt.reset([name] if batch else name)
    seen = []
    for k in range(40):
        x, r, y = tr.x[0, k], tr.r[0, k], (tr.y[0, k] if measured else None)
        if batch:
            padded = np.zeros((1, MAX_ORDER))
            padded[0, : plant.order] = x
            u = rt.step(padded, np.array([r]), None if y is None else np.array([y]))[0]
        else:
            u = rt.step(x, r, y)
            assert isinstance(u, float)
        state, _, ref, _ = rt.window()
        seen.append([u, rt.plan.copy(), rt.z.copy(), rt._u_prev.copy(), state.copy(), ref.copy()])
    return seen


@pytest.mark.parametrize("backend_name", ["torch", "onnx"])
@pytest.mark.parametrize("measured", [False, True])
def test_one_plant_steps_exactly_as_the_general_path(policy, backend_name, measured):
    fast, general = (PolicyRuntime(*policy, backend=backend_name) for _ in range(2))
    for name, amplitude in (("cstr", 1.5), ("hydraulic_actuator", -3.0), ("two_mass_spring", 2)):
        a = _run(fast, name, amplitude, measured, batch=False)
        b = _run(general, name, amplitude, measured, batch=True)
        for got, want in zip(a, b, strict=True):
            assert got[0] == want[0]
            for x, y in zip(got[1:], want[1:], strict=True):
                np.testing.assert_array_equal(x, y)


def test_the_plant_graph_is_smaller_and_computes_what_the_batch_session_does(policy):
    pol, _ = policy
    run = backend(pol, "onnx")
    rng = np.random.default_rng(0)
    one = onnx.load_from_string(onnx_bytes(pol, batch=1))
    for name in PLANTS:
        plant = load_plant(name)
        buffer = HistoryBuffer(np.array([plant.order]), 8, "integral" in pol.channels,
                               "previous_control" in pol.channels)  # fmt: skip
        single = run.plant(plant.tag, buffer.mask)
        tag = np.array([plant.tag])
        for scale in (1e-2, 1.0, 30.0):
            state = (rng.normal(size=buffer.mask.shape) * scale).astype(np.float32) * buffer.mask
            ref = (rng.normal(size=(1, 8)) * scale).astype(np.float32)
            np.testing.assert_array_equal(single(state, ref), run(state, buffer.mask, ref, tag))
        shrunk = plant_model(one, {"tag": tag, "mask": buffer.mask})
        assert len(onnx.load_from_string(shrunk).graph.node) < 0.8 * len(one.graph.node)


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
