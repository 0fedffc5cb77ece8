"""Rewrites of a static-shape ONNX graph for one plant at batch 1, and the graph they use.

A plant's batch-1 graph is mostly ONNX Runtime's per-node overhead: a few hundred kFLOP
over a hundred small nodes. :func:`freeze` makes known inputs (tag, mask) constants,
:func:`fold_constants` computes what depends on them alone with ONNX Runtime's unoptimised
kernels (as the batch session does), :func:`einsum_to_matmul` and :func:`prune` follow.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import onnx
from onnx import helper, numpy_helper, shape_inference

__all__ = [
    "Graph",
    "einsum_to_matmul",
    "fold_constants",
    "freeze",
    "prune",
    "run_subgraph",
]


@dataclass
class Graph:
    """A mutable view of an ONNX model: its nodes, constants, inputs and outputs.

    Attributes
    ----------
    nodes : list of NodeProto
        In topological order (``Constant`` nodes are moved into :attr:`consts`).
    consts : dict
        Name -> value of every initializer and constant.
    inputs, outputs : list of ValueInfoProto
    opset : list of OperatorSetIdProto
    ir_version : int
    """

    nodes: list[onnx.NodeProto]
    consts: dict[str, np.ndarray]
    inputs: list[onnx.ValueInfoProto]
    outputs: list[onnx.ValueInfoProto]
    opset: list[onnx.OperatorSetIdProto]
    ir_version: int
    _info: dict[str, tuple[tuple[int, ...] | None, int]] = field(default_factory=dict)

    @classmethod
    def from_model(cls, model: onnx.ModelProto) -> Graph:
        """The graph of ``model`` (``Constant`` nodes become constants)."""
        g = model.graph
        consts = {t.name: numpy_helper.to_array(t) for t in g.initializer}
        nodes = []
        for n in g.node:
            if n.op_type == "Constant" and n.attribute[0].name == "value":
                consts[n.output[0]] = numpy_helper.to_array(n.attribute[0].t)
            else:
                nodes.append(onnx.NodeProto())
                nodes[-1].CopyFrom(n)  # rewrites change nodes in place, never the model's
        return cls(
            nodes, consts, list(g.input), list(g.output), list(model.opset_import),
            model.ir_version,
        )  # fmt: skip

    def to_model(self) -> onnx.ModelProto:
        """The graph as a model (constants no node reads are left out)."""
        used = {i for n in self.nodes for i in n.input} | {o.name for o in self.outputs}
        inits = [numpy_helper.from_array(v, k) for k, v in self.consts.items() if k in used]
        graph = helper.make_graph(self.nodes, "policy", self.inputs, self.outputs, inits)
        return helper.make_model(graph, opset_imports=self.opset, ir_version=self.ir_version)

    def info(self, name: str) -> tuple[tuple[int, ...] | None, int]:
        """``(shape, elem_type)`` of a tensor (shape None where not static); see :meth:`infer`."""
        if name in self.consts:
            v = self.consts[name]
            return v.shape, helper.np_dtype_to_tensor_dtype(v.dtype)
        return self._info.get(name, (None, 0))

    def shape(self, name: str) -> tuple[int, ...] | None:
        """The static shape of a tensor, or None."""
        return self.info(name)[0]

    def infer(self) -> Graph:
        """Run ONNX shape inference; :meth:`info` reads its result. Returns ``self``."""
        inferred = shape_inference.infer_shapes(self.to_model(), data_prop=True)
        g = inferred.graph
        self._info = {}
        for v in [*g.input, *g.value_info, *g.output]:
            t = v.type.tensor_type
            dims = tuple(d.dim_value if d.HasField("dim_value") else -1 for d in t.shape.dim)
            static = t.HasField("shape") and all(d >= 0 for d in dims)
            self._info[v.name] = (dims if static else None, t.elem_type)
        return self

    def consumers(self) -> dict[str, list[onnx.NodeProto]]:
        """Tensor name -> the nodes that read it."""
        out: dict[str, list[onnx.NodeProto]] = {}
        for n in self.nodes:
            for i in n.input:
                out.setdefault(i, []).append(n)
        return out

    def sort(self) -> None:
        """Order :attr:`nodes` topologically (a rewrite may append nodes at the end)."""
        ready = set(self.consts) | {i.name for i in self.inputs} | {""}
        done: list[onnx.NodeProto] = []
        pending = list(self.nodes)
        while pending:
            rest = []
            for n in pending:
                if all(i in ready for i in n.input):
                    done.append(n)
                    ready.update(n.output)
                else:
                    rest.append(n)
            if len(rest) == len(pending):
                raise ValueError(f"the graph has a cycle or a missing input at {rest[0].name!r}")
            pending = rest
        self.nodes = done


def run_subgraph(
    graph: Graph,
    nodes: list[onnx.NodeProto],
    feeds: list[dict[str, np.ndarray]],
    outputs: list[str],
    consts: dict[str, np.ndarray] | None = None,
    out_type: int | None = None,
) -> list[list[np.ndarray]]:
    """Evaluate ``nodes`` of ``graph`` with ONNX Runtime on each of ``feeds``.

    Returns, per feed, the values of ``outputs``. ``consts`` replaces the graph's constants
    of the same names (e.g. in float64), and ``out_type`` (an ONNX element type) the
    outputs' types.
    """
    import onnxruntime as ort  # optional and heavy: only for the ONNX backend

    values = {**graph.consts, **(consts or {})}
    first = feeds[0]
    names = {i for n in nodes for i in n.input if i in values and i not in first}
    ins = [helper.make_tensor_value_info(k, _dtype(v), v.shape) for k, v in first.items()]
    outs = [helper.make_tensor_value_info(k, out_type or graph.info(k)[1], None) for k in outputs]
    inits = [numpy_helper.from_array(values[k], k) for k in names]
    model = helper.make_model(
        helper.make_graph(nodes, "part", ins, outs, inits),
        opset_imports=graph.opset,
        ir_version=graph.ir_version,
    )
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    sess = ort.InferenceSession(model.SerializeToString(), opts, ["CPUExecutionProvider"])
    return [[np.asarray(v) for v in sess.run(outputs, feed)] for feed in feeds]


def _dtype(v: np.ndarray) -> int:
    return helper.np_dtype_to_tensor_dtype(v.dtype)


def freeze(graph: Graph, values: dict[str, np.ndarray]) -> Graph:
    """Make the graph inputs named in ``values`` constants of those values."""
    for name, v in values.items():
        graph.consts[name] = np.asarray(v)
    graph.inputs = [i for i in graph.inputs if i.name not in values]
    return graph


def fold_constants(graph: Graph) -> Graph:
    """Evaluate each node whose inputs are all constant (see the module docstring)."""
    graph.infer()
    known = set(graph.consts)
    todo, rest = [], []
    for n in graph.nodes:
        shape = graph.shape(n.input[0]) if n.input else None
        if n.op_type == "Shape" and not n.attribute and shape is not None:
            graph.consts[n.output[0]] = np.array(shape, np.int64)
            known.add(n.output[0])
        elif all(i in known or not i for i in n.input):
            todo.append(n)
            known.update(o for o in n.output if o)
        else:
            rest.append(n)
    if todo:
        outs = [o for n in todo for o in n.output if o]
        graph.consts.update(zip(outs, run_subgraph(graph, todo, [{}], outs)[0], strict=True))
    graph.nodes = rest
    return graph


def _attr(node: onnx.NodeProto, name: str, default: Any) -> Any:
    for a in node.attribute:
        if a.name == name:
            return helper.get_attribute_value(a)
    return default


def _split_equation(eq: str) -> tuple[str, str, str] | None:
    eq = eq.replace(" ", "")
    if "." in eq or "->" not in eq:
        return None
    lhs, out = eq.split("->")
    ops = lhs.split(",")
    if len(ops) != 2 or any(len(set(s)) != len(s) for s in (*ops, out)):
        return None
    a, b = ops
    if set(out) - set(a) - set(b) or (set(a) ^ set(b)) - set(out):
        return None  # a letter summed over one operand alone
    return a, b, out


def einsum_to_matmul(graph: Graph) -> Graph:
    """Rewrite two-operand ``Einsum`` nodes of static shapes as ``MatMul`` (see module doc).

    ``a, b -> out``: batch letters (in all three), contracted ones (in ``a`` and ``b``) and
    free ones; each operand is transposed to ``(batch, free, contracted)`` order and
    reshaped to three axes (two where the batch letters' size is one), multiplied, and
    brought back to ``out``'s axes.
    """
    graph.infer()
    nodes: list[onnx.NodeProto] = []
    for n in graph.nodes:
        parts = None
        if n.op_type == "Einsum":
            parts = _split_equation(_attr(n, "equation", b"").decode())
        shapes = [graph.shape(i) for i in n.input]
        if parts is None or len(n.input) != 2 or shapes[0] is None or shapes[1] is None:
            nodes.append(n)
        else:
            _einsum_nodes(graph, nodes, n, parts, (shapes[0], shapes[1]))
    graph.nodes = nodes
    return graph


def _einsum_nodes(
    graph: Graph,
    nodes: list[onnx.NodeProto],
    n: onnx.NodeProto,
    parts: tuple[str, str, str],
    shapes: tuple[tuple[int, ...], tuple[int, ...]],
) -> None:
    """Append the ``MatMul`` form of Einsum node ``n`` (see :func:`einsum_to_matmul`)."""
    a, b, out = parts
    dim = {**dict(zip(a, shapes[0], strict=True)), **dict(zip(b, shapes[1], strict=True))}
    batch = [c for c in out if c in a and c in b]
    free_a = [c for c in out if c in a and c not in b]
    free_b = [c for c in out if c in b and c not in a]
    summed = [c for c in a if c in b and c not in out]

    def size(cs: list[str]) -> int:
        return int(np.prod([dim[c] for c in cs]))

    p = n.output[0] + "/mm"
    lead = (size(batch),) if size(batch) > 1 else ()  # one product at batch 1: 2-d
    sa = (*lead, size(free_a), size(summed))
    sb = (*lead, size(summed), size(free_b))
    x = _arrange(graph, nodes, n.input[0], a, batch + free_a + summed, sa, dim, p + "a")
    y = _arrange(graph, nodes, n.input[1], b, batch + summed + free_b, sb, dim, p + "b")
    nodes.append(helper.make_node("MatMul", [x, y], [p]))
    order = batch + free_a + free_b
    graph.consts[p + "/shape"] = np.array([dim[c] for c in order], np.int64)
    perm = [order.index(c) for c in out]
    last = n.output[0] if perm == sorted(perm) else p + "/r"
    nodes.append(helper.make_node("Reshape", [p, p + "/shape"], [last]))
    if last != n.output[0]:
        nodes.append(helper.make_node("Transpose", [last], [n.output[0]], perm=perm))


def _arrange(
    graph: Graph,
    nodes: list[onnx.NodeProto],
    name: str,
    letters: str,
    order: list[str],
    shape: tuple[int, ...],
    dim: dict[str, int],
    prefix: str,
) -> str:
    """Transpose ``name`` (axes ``letters``) to ``order`` and reshape it to ``shape``."""
    perm = [letters.index(c) for c in order]
    if perm != sorted(perm):
        nodes.append(helper.make_node("Transpose", [name], [prefix + "/t"], perm=perm))
        name = prefix + "/t"
    if tuple(dim[c] for c in order) != shape:
        graph.consts[prefix + "/shape"] = np.array(shape, np.int64)
        nodes.append(helper.make_node("Reshape", [name, prefix + "/shape"], [prefix + "/r"]))
        name = prefix + "/r"
    return name


def prune(graph: Graph) -> Graph:
    """Remove the nodes no graph output depends on."""
    need = {o.name for o in graph.outputs}
    kept = []
    for n in reversed(graph.nodes):
        if any(o in need for o in n.output if o):
            kept.append(n)
            need.update(n.input)
    graph.nodes = kept[::-1]
    graph.consts = {k: v for k, v in graph.consts.items() if k in need}
    return graph
