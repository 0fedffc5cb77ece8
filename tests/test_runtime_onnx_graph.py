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
from generalist_control.deploy.onnx_concat import hoist_concats
from generalist_control.deploy.onnx_graph import Graph, drop_trivial, einsum_to_matmul
from generalist_control.deploy.onnx_layout import tidy_reshapes


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


def test_a_softmax_over_one_element_and_its_product_are_dropped():
    consts = {"w": np.ones((1, 1), np.float32)}
    nodes = [
        helper.make_node("Softmax", ["a"], ["p"], axis=-1),
        helper.make_node("MatMul", ["p", "v"], ["y"]),
    ]
    g = _graph(nodes, {"a": (2, 1, 1), "v": (2, 1, 3)}, "y", consts)
    rng = np.random.default_rng(2)
    feeds = {"a": rng.normal(size=(2, 1, 1)).astype(np.float32),
             "v": rng.normal(size=(2, 1, 3)).astype(np.float32)}  # fmt: skip
    drop_trivial(g)
    assert [n.op_type for n in g.nodes] == ["Identity"]
    np.testing.assert_array_equal(_run_graph(g, feeds), feeds["v"])


def _experts() -> tuple[Graph, dict[str, np.ndarray], np.ndarray]:
    """Three parallel branches of x (Gemm, ReLU, LayerNorm of their own scales, Gemm), their
    Concat and a last layer; and the numpy reference of the output."""
    rng = np.random.default_rng(3)
    f32 = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    x = f32(1, 6)
    consts, nodes, outs, ref = {"Wo": f32(12, 2), "bo": f32(2)}, [], [], []
    for i in range(3):
        consts |= {f"W{i}": f32(6, 4), f"b{i}": f32(4), f"V{i}": f32(4, 4), f"c{i}": f32(4),
                   f"g{i}": f32(4) + 1, f"o{i}": f32(4)}  # fmt: skip
        nodes += [
            helper.make_node("Gemm", ["x", f"W{i}", f"b{i}"], [f"h{i}"]),
            helper.make_node("Relu", [f"h{i}"], [f"r{i}"]),
            helper.make_node(
                "LayerNormalization", [f"r{i}", f"g{i}", f"o{i}"], [f"n{i}"], axis=-1, epsilon=1e-5
            ),  # fmt: skip
            helper.make_node("Gemm", [f"n{i}", f"V{i}", f"c{i}"], [f"e{i}"]),
        ]
        outs.append(f"e{i}")
        r = np.maximum(x.astype(np.float64) @ consts[f"W{i}"] + consts[f"b{i}"], 0)
        n = (r - r.mean(-1, keepdims=True)) / np.sqrt(r.var(-1, keepdims=True) + 1e-5)
        ref.append((n * consts[f"g{i}"] + consts[f"o{i}"]) @ consts[f"V{i}"] + consts[f"c{i}"])
    nodes += [helper.make_node("Concat", outs, ["cat"], axis=-1),
              helper.make_node("Gemm", ["cat", "Wo", "bo"], ["y"])]  # fmt: skip
    want = np.concatenate(ref, -1) @ consts["Wo"] + consts["bo"]
    return _graph(nodes, {"x": (1, 6)}, "y", consts), {"x": x}, want


def test_parallel_branches_are_joined_into_one_wider_stack():
    g, feeds, want = _experts()
    n = len(g.nodes)
    joined = tidy_reshapes(fold_affine(hoist_concats(g), exact=False))
    ops = [m.op_type for m in joined.nodes]
    assert len(joined.nodes) < n - 6
    assert ops.count("LayerNormalization") == 1 and ops.count("Gemm") <= 3
    np.testing.assert_allclose(_run_graph(joined, feeds), want, rtol=1e-5, atol=1e-6)


def test_a_concat_of_unlike_or_shared_branches_is_left_alone():
    nodes = [
        helper.make_node("Relu", ["a"], ["p"]),
        helper.make_node("Sigmoid", ["b"], ["q"]),
        helper.make_node("Concat", ["p", "q"], ["y"], axis=-1),
        helper.make_node("Relu", ["b"], ["s"]),
        helper.make_node("Concat", ["y", "s"], ["t"], axis=-1),
        helper.make_node("Add", ["t", "t"], ["z"]),
    ]
    g = _graph(nodes, {"a": (2, 3), "b": (2, 3)}, "z", {})
    g.outputs.append(helper.make_tensor_value_info("y", TensorProto.FLOAT, None))  # y is read
    before = [(m.op_type, list(m.input)) for m in g.nodes]
    assert [(m.op_type, list(m.input)) for m in hoist_concats(g).nodes] == before


def test_an_inexact_fold_composes_products_of_products():
    """Two layers and a scaling without a nonlinearity between: one Gemm, to float32."""
    rng = np.random.default_rng(4)
    f32 = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    consts = {"W1": f32(5, 7), "b1": f32(7), "W2": f32(7, 3), "d": np.float32(3.0) * f32(3)}
    nodes = [
        helper.make_node("MatMul", ["x", "W1"], ["h"]),
        helper.make_node("Add", ["h", "b1"], ["hb"]),
        helper.make_node("MatMul", ["hb", "W2"], ["o"]),
        helper.make_node("Div", ["o", "d"], ["y"]),
    ]
    x = f32(2, 5)
    want = (x.astype(np.float64) @ consts["W1"] + consts["b1"]) @ consts["W2"] / consts["d"]
    exact = fold_affine(_graph(nodes, {"x": (2, 5)}, "y", dict(consts)))
    assert len(exact.nodes) >= 2  # bit-exact: cut before the second rounding
    g = fold_affine(_graph(nodes, {"x": (2, 5)}, "y", dict(consts)), exact=False)
    assert [m.op_type for m in g.nodes] == ["Gemm"]
    np.testing.assert_allclose(_run_graph(g, {"x": x}), want, rtol=1e-5, atol=1e-6)
