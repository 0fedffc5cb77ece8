"""A mutable view of a static-shape ONNX graph and the rewrites that shrink it.

A plant's batch-1 graph costs mostly ONNX Runtime's per-node overhead, so each rewrite
leaves fewer nodes computing the same floats (docs/notes/deploy-speed.md).
"""

from __future__ import annotations

from collections.abc import Sequence
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
    "session",
    "tidy_reshapes",
]

#: Elementwise functions of one tensor (no attribute changes what "elementwise" means).
_ELEMENTWISE = {
    "Relu", "Sigmoid", "Tanh", "Neg", "Abs", "Exp", "Log", "Sqrt", "Reciprocal", "Softplus",
    "Softsign", "Elu", "Selu", "LeakyRelu", "HardSigmoid", "Erf", "Floor", "Ceil", "Sign",
}  # fmt: skip
_SHAPES = {"Reshape", "Squeeze", "Unsqueeze", "Flatten"}


@dataclass
class Graph:
    """An ONNX model's nodes (in topological order), constants, inputs and outputs."""

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


def session(
    model: bytes, arena: bool = True, disabled: Sequence[str] = (), optimise: bool = True
) -> Any:
    """An ONNX Runtime session for one thread, every graph optimisation on but ``disabled``.

    ``arena``: the memory arena, of use only where shapes change from call to call;
    ``optimise`` False: no graph optimisation at all (the graph runs as written).
    """
    import onnxruntime as ort  # optional and heavy: only for the ONNX backend

    opts = ort.SessionOptions()
    opts.enable_cpu_mem_arena = arena
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    level = ort.GraphOptimizationLevel
    opts.graph_optimization_level = level.ORT_ENABLE_ALL if optimise else level.ORT_DISABLE_ALL
    opts.log_severity_level = 3  # warnings of the optimiser are not the user's business
    return ort.InferenceSession(
        model, opts, providers=["CPUExecutionProvider"], disabled_optimizers=list(disabled)
    )


def run_subgraph(
    graph: Graph,
    nodes: list[onnx.NodeProto],
    feeds: list[dict[str, np.ndarray]],
    outputs: list[str],
    consts: dict[str, np.ndarray] | None = None,
    out_type: int | None = None,
) -> list[list[np.ndarray]]:
    """Per feed, the values of ``outputs`` of ``nodes`` run by ONNX Runtime (unoptimised).

    ``consts`` replaces the graph's constants of the same names (e.g. in float64), and
    ``out_type`` (an ONNX element type) the outputs' types.
    """
    values = {**graph.consts, **(consts or {})}
    first = feeds[0]
    names = {i for n in nodes for i in n.input if i in values and i not in first}
    ins = [
        helper.make_tensor_value_info(k, helper.np_dtype_to_tensor_dtype(v.dtype), v.shape)
        for k, v in first.items()
    ]
    outs = [helper.make_tensor_value_info(k, out_type or graph.info(k)[1], None) for k in outputs]
    inits = [numpy_helper.from_array(values[k], k) for k in names]
    model = helper.make_model(
        helper.make_graph(nodes, "part", ins, outs, inits),
        opset_imports=graph.opset,
        ir_version=graph.ir_version,
    )
    sess = session(model.SerializeToString(), optimise=False)
    return [[np.asarray(v) for v in sess.run(outputs, feed)] for feed in feeds]


def freeze(graph: Graph, values: dict[str, np.ndarray]) -> Graph:
    """Make the graph inputs named in ``values`` constants of those values."""
    for name, v in values.items():
        graph.consts[name] = np.asarray(v)
    graph.inputs = [i for i in graph.inputs if i.name not in values]
    return graph


def fold_constants(graph: Graph) -> Graph:
    """Compute once each node whose inputs are all constant, as the batch session does."""
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
    """Rewrite two-operand ``Einsum`` nodes of static shapes as ``MatMul``.

    Each operand is transposed to ``(batch, free, contracted)`` order and reshaped to three
    axes (two where the batch is one), multiplied, and brought back to the output's axes.
    """
    graph.infer()
    nodes: list[onnx.NodeProto] = []
    for n in graph.nodes:
        parts = None
        if n.op_type == "Einsum":
            eq = [helper.get_attribute_value(a) for a in n.attribute if a.name == "equation"]
            parts = _split_equation(eq[0].decode() if eq else "")
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

    def arrange(name: str, letters: str, order: list[str], shape: tuple, pre: str) -> str:
        """Transpose ``name`` (axes ``letters``) to ``order`` and reshape it to ``shape``."""
        perm = [letters.index(c) for c in order]
        if perm != sorted(perm):
            nodes.append(helper.make_node("Transpose", [name], [pre + "/t"], perm=perm))
            name = pre + "/t"
        if tuple(dim[c] for c in order) != shape:
            graph.consts[pre + "/shape"] = np.array(shape, np.int64)
            nodes.append(helper.make_node("Reshape", [name, pre + "/shape"], [pre + "/r"]))
            name = pre + "/r"
        return name

    p = n.output[0] + "/mm"
    lead = (size(batch),) if size(batch) > 1 else ()  # one product at batch 1: 2-d
    sa = (*lead, size(free_a), size(summed))
    sb = (*lead, size(summed), size(free_b))
    x = arrange(n.input[0], a, batch + free_a + summed, sa, p + "a")
    y = arrange(n.input[1], b, batch + summed + free_b, sb, p + "b")
    nodes.append(helper.make_node("MatMul", [x, y], [p]))
    order = batch + free_a + free_b
    graph.consts[p + "/shape"] = np.array([dim[c] for c in order], np.int64)
    perm = [order.index(c) for c in out]
    last = n.output[0] if perm == sorted(perm) else p + "/r"
    nodes.append(helper.make_node("Reshape", [p, p + "/shape"], [last]))
    if last != n.output[0]:
        nodes.append(helper.make_node("Transpose", [last], [n.output[0]], perm=perm))


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
    """Rewrite reshapes until none applies, so fewer of them run; drop what is unused.

    Reshape-like nodes become static ``Reshape``, chains of them one, those to their input's
    own shape go, and they move past elementwise nodes to meet and cancel.
    """
    for _ in range(50):
        graph.infer()
        if not (_collapse(graph) | _sink(graph)):
            break
        prune(graph)
    return prune(graph)
