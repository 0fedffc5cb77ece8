"""Fewer reshapes in a static-shape ONNX graph: each one is a node ONNX Runtime runs.

:func:`tidy_reshapes` writes reshape-like nodes as static ``Reshape``, merges chains of them,
drops those to their input's own shape, and moves them past elementwise nodes so that they
meet and cancel. None of this computes a value: it moves elements.
"""

from __future__ import annotations

import numpy as np
import onnx

from generalist_control.deploy.onnx_graph import Graph, prune

__all__ = ["tidy_reshapes"]

#: Elementwise functions of one tensor (no attribute changes what "elementwise" means).
_ELEMENTWISE = {
    "Relu", "Sigmoid", "Tanh", "Neg", "Abs", "Exp", "Log", "Sqrt", "Reciprocal", "Softplus",
    "Softsign", "Elu", "Selu", "LeakyRelu", "HardSigmoid", "Erf", "Floor", "Ceil", "Sign",
}  # fmt: skip
_SHAPES = {"Reshape", "Squeeze", "Unsqueeze", "Flatten"}


def _static_reshape(graph: Graph, node: onnx.NodeProto) -> bool:
    """Rewrite a reshape-like node as ``Reshape`` to its static output shape (if it is one)."""
    if not node.input or not node.output:
        return False
    src, out = graph.shape(node.input[0]), graph.shape(node.output[0])
    if src is None or out is None:
        return False
    if node.op_type == "Transpose":
        perm = [a.ints for a in node.attribute if a.name == "perm"]
        order = list(perm[0]) if perm else list(range(len(src)))[::-1]
        moved = [a for a in order if src[a] != 1]
        if moved != sorted(moved):
            return False
    elif node.op_type not in _SHAPES:
        return False
    name = node.output[0] + "/static_shape"
    graph.consts[name] = np.array(out, np.int64)
    node.op_type = "Reshape"
    node.input[:] = [node.input[0], name]
    del node.attribute[:]
    return True


def _collapse(graph: Graph) -> bool:
    """Reshape-like nodes as static reshapes; chains of them as one; identities dropped."""
    changed = False
    producer = {o: n for n in graph.nodes for o in n.output}
    outputs = {o.name for o in graph.outputs}
    alias: dict[str, str] = {}
    kept = []
    for n in graph.nodes:
        n.input[:] = [alias.get(i, i) for i in n.input]
        was = n.op_type
        static = was in _SHAPES | {"Transpose"} and _static_reshape(graph, n)
        changed |= static and was != "Reshape"
        if static:
            inner = producer.get(n.input[0])
            if inner is not None and inner.op_type == "Reshape":
                n.input[0] = inner.input[0]  # its shape is static: the input's does not matter
                changed = True
            if graph.shape(n.input[0]) == graph.shape(n.output[0]) and n.output[0] not in outputs:
                alias[n.output[0]] = n.input[0]
                changed = True
                continue
        kept.append(n)
    graph.nodes = kept
    return changed


def _sink(graph: Graph) -> bool:
    """``f(Reshape(x))`` as ``Reshape(f(x))`` for elementwise ``f`` (the reshape read once)."""
    readers = graph.consumers()
    producer = {o: n for n in graph.nodes for o in n.output}
    outputs = {o.name for o in graph.outputs}
    changed = False
    for n in list(graph.nodes):
        r = producer.get(n.input[0]) if n.op_type in _ELEMENTWISE and n.input else None
        if r is None or r.op_type != "Reshape" or len(readers.get(r.output[0], ())) != 1:
            continue
        shape = graph.shape(n.output[0])
        if r.output[0] in outputs or shape is None:
            continue
        inner, out = n.output[0] + "/before_reshape", n.output[0]
        n.input[0], n.output[0] = r.input[0], inner
        r.input[:] = [inner, out + "/static_shape"]
        r.output[0] = out
        graph.consts[out + "/static_shape"] = np.array(shape, np.int64)
        changed = True
    if changed:
        graph.sort()
    return changed


def tidy_reshapes(graph: Graph) -> Graph:
    """Apply the rewrites of the module docstring until none applies; drop what is unused."""
    for _ in range(50):
        graph.infer()
        if not (_collapse(graph) | _sink(graph)):
            break
        prune(graph)
    return prune(graph)
