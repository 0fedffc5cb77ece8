"""The ONNX graph rewrites behind a plant's batch-1 graph, one by one, on small graphs.

Each rewritten graph is run by ONNX Runtime beside the graph it came from: einsums as
matrix products (to float32 rounding), folded linear chains and tidied reshapes to the bit.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from generalist_control.deploy.onnx_affine import fold_affine
from generalist_control.deploy.onnx_graph import Graph, einsum_to_matmul, tidy_reshapes


def _graph(nodes, inputs, output, consts) -> Graph:
    vi = [helper.make_tensor_value_info(k, TensorProto.FLOAT, s) for k, s in inputs.items()]
    out = [helper.make_tensor_value_info(output, TensorProto.FLOAT, None)]
    inits = [numpy_helper.from_array(v, k) for k, v in consts.items()]
    model = helper.make_model(
        helper.make_graph(nodes, "g", vi, out, inits), opset_imports=[helper.make_opsetid("", 17)]
    )
    return Graph.from_model(model)


def _run_graph(graph: Graph, feeds: dict[str, np.ndarray]) -> np.ndarray:
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    model = graph.to_model().SerializeToString()
    return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"]).run(None, feeds)[
        0
    ]


@pytest.mark.parametrize(
    ("equation", "shapes"),
    [
        ("bm,bmk->bk", [(2, 3), (2, 3, 4)]),
        ("bkf,bf->bk", [(2, 3, 5), (2, 5)]),
        ("ij,jk->ik", [(3, 4), (4, 5)]),
        ("abc,cd->dab", [(2, 3, 4), (4, 5)]),
    ],
)
def test_einsum_becomes_matmul(equation, shapes):
    rng = np.random.default_rng(0)
    feeds = {n: rng.normal(size=s).astype(np.float32) for n, s in zip("ab", shapes, strict=True)}
    g = _graph([helper.make_node("Einsum", ["a", "b"], ["y"], equation=equation)],
               {k: v.shape for k, v in feeds.items()}, "y", {})  # fmt: skip
    got = _run_graph(einsum_to_matmul(g), feeds)
    assert "Einsum" not in {n.op_type for n in g.nodes}
    np.testing.assert_allclose(got, np.einsum(equation, *feeds.values()), rtol=1e-5, atol=1e-6)


def _chain() -> tuple[Graph, dict[str, np.ndarray]]:
    """x (1, 6, 5) -> masked, sliced, per-row layer, ReLU, a second layer, flattened: a
    chain of moves and products whose folds must compute the same floats."""
    rng = np.random.default_rng(1)
    f32 = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    consts = {
        "mask": np.array([1, 1, 1, 0, 1], np.float32), "s0": np.array([0, 0, 0], np.int64),
        "s1": np.array([1, 6, 4], np.int64), "W1": f32(4, 8), "b1": f32(8), "W2": f32(8, 3),
        "b2": f32(3), "flat": np.array([1, 18], np.int64), "half": np.array(0.5, np.float32),
    }  # fmt: skip
    nodes = [
        helper.make_node("Mul", ["x", "mask"], ["xm"]),
        helper.make_node("Slice", ["xm", "s0", "s1"], ["xs"]),
        helper.make_node("MatMul", ["xs", "W1"], ["h0"]),
        helper.make_node("Add", ["h0", "b1"], ["h1"]),
        helper.make_node("Relu", ["h1"], ["h"]),
        helper.make_node("MatMul", ["h", "W2"], ["o0"]),
        helper.make_node("Add", ["o0", "b2"], ["o1"]),
        helper.make_node("Mul", ["o1", "half"], ["o2"]),
        helper.make_node("Reshape", ["o2", "flat"], ["o3"]),
        helper.make_node("MatMul", ["o3", "W3"], ["y"]),  # a second product: not folded in
    ]
    consts["W3"] = f32(18, 2)
    return _graph(nodes, {"x": (1, 6, 5)}, "y", consts), {"x": f32(1, 6, 5)}


def test_folded_chains_compute_the_same_floats_with_fewer_nodes():
    g, feeds = _chain()
    want = _run_graph(g, feeds)
    n = len(g.nodes)
    folded = tidy_reshapes(fold_affine(g))
    assert len(folded.nodes) < n
    np.testing.assert_array_equal(_run_graph(folded, feeds), want)
