"""Parallel branches of a static-shape ONNX graph joined into one, above their ``Concat``.

A ``Concat`` along the last axis of 2-d tensors that parallel nodes of one kind compute (each
read by the ``Concat`` alone) is the output of one node of that kind on the joined inputs.
:func:`hoist_concats` rewrites, until nothing changes:

* ``Concat(f(x_1), .., f(x_K))`` as ``f(Concat(x_1, .., x_K))`` for an elementwise ``f``;
* ``Concat(Gemm(x_1, W_1, c_1), ..)`` as one ``Gemm`` of the joined distinct inputs with the
  block matrix of the ``W_i`` (one input read by all: the ``W_i`` side by side);
* ``Concat(LayerNormalization(x_1; g_1, b_1), ..)`` of equal widths as one normalisation of
  the joined inputs seen as ``(rows, K, width)``, then the scales and offsets as a product
  and a sum with constants (which :func:`~generalist_control.deploy.onnx_affine.fold_affine`
  folds into a linear layer that follows).

So K experts, each a stack of layers, become one stack of wider layers. A joined ``Gemm``
sums the same products as its branches, but ONNX Runtime may block a wider product
differently: the result agrees to float32 rounding, not to the bit.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import helper

from generalist_control.deploy.onnx_graph import Graph, prune

__all__ = ["hoist_concats"]

#: Elementwise functions of one tensor (no attribute changes what "elementwise" means).
_ELEMENTWISE = {
    "Relu", "Sigmoid", "Tanh", "Neg", "Abs", "Exp", "Log", "Sqrt", "Reciprocal", "Softplus",
    "Softsign", "Elu", "Selu", "LeakyRelu", "HardSigmoid", "Erf", "Floor", "Ceil", "Sign",
}  # fmt: skip


def _attr(node: onnx.NodeProto, name: str, default: object) -> object:
    for a in node.attribute:
        if a.name == name:
            return helper.get_attribute_value(a)
    return default


def _same_attributes(nodes: list[onnx.NodeProto]) -> bool:
    first = sorted(a.SerializeToString() for a in nodes[0].attribute)
    return all(sorted(a.SerializeToString() for a in n.attribute) == first for n in nodes[1:])


class _Hoist:
    """One rewrite of a ``Concat`` (``concat``) of the outputs of nodes ``branches``."""

    def __init__(self, graph: Graph, concat: onnx.NodeProto, branches: list[onnx.NodeProto]):
        self.graph, self.concat, self.branches = graph, concat, branches
        self.out = concat.output[0]
        self.nodes: list[onnx.NodeProto] = []

    def name(self, what: str) -> str:
        return f"{self.out}/hoisted/{what}"

    def const(self, what: str, value: np.ndarray) -> str:
        name = self.name(what) + "/value"
        self.graph.consts[name] = value
        return name

    def joined(self, inputs: list[str]) -> str:
        """The ``Concat`` of ``inputs`` along the last axis (one input: itself)."""
        if len(inputs) == 1:
            return inputs[0]
        self.nodes.append(helper.make_node("Concat", inputs, [self.name("in")], axis=-1))
        return self.name("in")

    def elementwise(self) -> bool:
        if not _same_attributes(self.branches):
            return False
        first = self.branches[0]
        x = self.joined([b.input[0] for b in self.branches])
        node = helper.make_node(first.op_type, [x], [self.out])
        node.attribute.extend(first.attribute)
        self.nodes.append(node)
        return True

    def gemm(self) -> bool:
        g = self.graph
        parts = []
        for b in self.branches:
            shape = g.shape(b.input[0])
            if (
                len(b.input) < 2 or b.input[1] not in g.consts or _attr(b, "transA", 0)
                or (len(b.input) > 2 and b.input[2] and b.input[2] not in g.consts)
                or shape is None or len(shape) != 2
            ):  # fmt: skip
                return False
            W = g.consts[b.input[1]].astype(np.float64)
            W = (W.T if _attr(b, "transB", 0) else W) * float(_attr(b, "alpha", 1.0))  # type: ignore[arg-type]
            c = np.zeros(W.shape[1])
            if len(b.input) > 2 and b.input[2]:
                beta = float(_attr(b, "beta", 1.0))  # type: ignore[arg-type]
                full = np.broadcast_to(g.consts[b.input[2]] * beta, (shape[0], W.shape[1]))
                if np.any(full != full[0]):
                    return False
                c = full[0]
            parts.append((b.input[0], W, c))
        inputs = list(dict.fromkeys(x for x, _, _ in parts))
        at, rows = 0, {}
        for x in inputs:
            rows[x] = at
            at += next(len(W) for y, W, _ in parts if y == x)
        big = np.zeros((at, sum(W.shape[1] for _, W, _ in parts)))
        col = 0
        for x, W, _ in parts:
            big[rows[x] : rows[x] + len(W), col : col + W.shape[1]] = W
            col += W.shape[1]
        bias = np.concatenate([c for _, _, c in parts])
        W_name = self.const("W", big.astype(np.float32))
        c_name = self.const("c", bias.astype(np.float32))
        self.nodes.append(
            helper.make_node("Gemm", [self.joined(inputs), W_name, c_name], [self.out])
        )
        return True

    def layernorm(self) -> bool:
        g, first = self.graph, self.branches[0]
        shapes = {g.shape(b.input[0]) for b in self.branches}
        shape = shapes.pop() if len(shapes) == 1 else None
        if (
            shape is None or len(shape) != 2 or not _same_attributes(self.branches)
            or _attr(first, "axis", -1) not in (-1, 1)
            or any(len([o for o in b.output if o]) != 1 for b in self.branches)
            or any(i not in g.consts for b in self.branches for i in b.input[1:] if i)
        ):  # fmt: skip
            return False
        rows, width, k = shape[0], shape[1], len(self.branches)
        scale = np.stack([np.broadcast_to(g.consts[b.input[1]], (width,)) for b in self.branches])
        bias = np.stack([
            np.broadcast_to(g.consts[b.input[2]], (width,)) if len(b.input) > 2 and b.input[2]
            else np.zeros(width, np.float32) for b in self.branches
        ])  # fmt: skip
        x = self.joined([b.input[0] for b in self.branches])
        grouped = self.const("grouped", np.array([rows, k, width], np.int64))
        self.nodes.append(helper.make_node("Reshape", [x, grouped], [self.name("grouped")]))
        same = bool(np.all(scale == scale[0]) and np.all(bias == bias[0]))
        s = self.const("scale", (scale[0] if same else np.ones(width)).astype(np.float32))
        o = self.const("offset", (bias[0] if same else np.zeros(width)).astype(np.float32))
        ln = helper.make_node("LayerNormalization", [self.name("grouped"), s, o],
                              [self.name("normal")])  # fmt: skip
        ln.attribute.extend(first.attribute)
        self.nodes.append(ln)
        y = self.name("normal")
        if not same:
            S, B = (
                self.const("S", scale.astype(np.float32)),
                self.const("B", bias.astype(np.float32)),
            )
            scaled, moved = self.name("scaled"), self.name("moved")
            self.nodes.append(helper.make_node("Mul", [y, S], [scaled]))
            self.nodes.append(helper.make_node("Add", [scaled, B], [moved]))
            y = self.name("moved")
        flat = self.const("flat", np.array([rows, k * width], np.int64))
        self.nodes.append(helper.make_node("Reshape", [y, flat], [self.out]))
        return True


def _candidate(graph: Graph, n: onnx.NodeProto, producer, readers, outputs) -> _Hoist | None:
    shape = graph.shape(n.output[0])
    if n.op_type != "Concat" or shape is None or len(shape) != 2 or len(n.input) < 2:
        return None
    if int(_attr(n, "axis", 0)) % 2 != 1:  # type: ignore[call-overload]
        return None
    branches: list[onnx.NodeProto] = []
    for i in n.input:
        b = producer.get(i)
        if b is None or len(readers.get(i, ())) != 1 or i in outputs:
            return None
        if branches and b.op_type != branches[0].op_type:
            return None
        branches.append(b)
    return _Hoist(graph, n, branches)


def _hoist_one(graph: Graph) -> bool:
    readers = graph.consumers()
    producer = {o: n for n in graph.nodes for o in n.output}
    outputs = {o.name for o in graph.outputs}
    for n in graph.nodes:
        h = _candidate(graph, n, producer, readers, outputs)
        if h is None:
            continue
        op = h.branches[0].op_type
        if op in _ELEMENTWISE:
            done = h.elementwise()
        elif op == "Gemm":
            done = h.gemm()
        elif op == "LayerNormalization":
            done = h.layernorm()
        else:
            done = False
        if done:
            gone = {id(b) for b in h.branches} | {id(n)}
            graph.nodes = [m for m in graph.nodes if id(m) not in gone] + h.nodes
            graph.sort()
            return True
    return False


def hoist_concats(graph: Graph) -> Graph:
    """Apply the rewrites of the module docstring until none applies; drop what is unused."""
    for _ in range(100):
        graph.infer()
        if not _hoist_one(graph):
            break
    return prune(graph)
