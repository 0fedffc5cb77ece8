"""Fold chains of linear nodes of a static-shape ONNX graph into single ``Gemm`` nodes.

A chain that rounds at most once per output element (one product sum of moved source
elements; a chain that would round twice is cut there) folds into the same floats.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto, helper

from generalist_control.deploy.onnx_graph import Graph, prune, run_subgraph

__all__ = ["fold_affine"]

#: Data movement: the output's elements are input elements (inputs past ``_DATA`` constant).
_MOVES = {
    "Identity", "Reshape", "Flatten", "Squeeze", "Unsqueeze", "Transpose", "Slice", "Gather",
    "Split", "Concat", "Expand", "Neg",
}  # fmt: skip
_DATA = {"Reshape": 1, "Slice": 1, "Gather": 1, "Expand": 1, "Split": 1, "Squeeze": 1,
         "Unsqueeze": 1}  # fmt: skip
#: Largest folded matrix (entries) of a chain that is not applied row by row.
MAX_ENTRIES = 1 << 14

# What an affine tensor's elements are, from exact to rounded: moved source elements, the
# same with constants among them, one product sum, one product sum plus an offset (or any
# single rounded sum). A node whose inputs are beyond what it may take gets them cut.
SEL, SELC, PROD, DONE = 0, 1, 2, 3


@dataclass
class _Chains:
    """The affine tensors of a graph: their state, sources, inputs to follow, and cuts."""

    state: dict[str, int]
    sources: dict[str, frozenset[str]]
    follow: dict[int, list[str]]
    producer: dict[str, onnx.NodeProto]
    cuts: set[str]


def _exact_scale(c: np.ndarray, divide: bool) -> bool:
    """Whether multiplying (dividing) by ``c`` is exact: zeros (not for a divisor), +-2^k."""
    mant = np.abs(np.frexp(np.asarray(c, np.float64))[0])
    return bool(np.all((mant == 0.5) | ((mant == 0) & (not divide))))


def _kind(node: onnx.NodeProto, consts: dict[str, np.ndarray]) -> str | None:
    """How ``node`` is affine in its non-constant inputs (None: it is not)."""
    op, ins = node.op_type, list(node.input)
    dyn = [i for i in ins if i and i not in consts]
    if not dyn:
        return None
    if op in _MOVES:
        return None if any(i in dyn for i in ins[_DATA.get(op, len(ins)) :]) else "move"
    if op in ("Add", "Sub"):
        return "add" if len(dyn) == 2 else "offset"
    if op in ("Mul", "Div") and len(ins) == 2 and len(dyn) == 1:
        if op == "Div" and ins[1] in dyn:
            return None
        c = consts[ins[1] if ins[0] in dyn else ins[0]]
        if _exact_scale(c, op == "Div"):
            return "scale"
        # x * c is the product a Gemm computes; x / c is not x * (1 / c) in floats
        return "product" if op == "Mul" else None
    # a product with constant weights on the right, as the folded Gemm computes it: the
    # kernel sums along the same axis in the same order (with the weights on the left, as a
    # matrix times a column, it may sum in another order)
    if op in ("MatMul", "Gemm") and len(dyn) == 1 and dyn[0] == ins[0]:
        return "gemm" if op == "Gemm" and len(ins) > 2 and ins[2] else "product"
    return None


#: per kind: the most rounded input state it takes, and its output's state (None: the input's)
_RULES = {"move": (DONE, None), "scale": (DONE, None), "product": (SEL, PROD),
          "gemm": (SEL, DONE), "offset": (PROD, DONE), "add": (SELC, DONE)}  # fmt: skip


def _chains(graph: Graph) -> _Chains:
    """Classify the graph's tensors by how rounded they are (``SEL`` to ``DONE``)."""
    ch = _Chains({}, {}, {}, {}, set())
    readers = graph.consumers()
    for n in graph.nodes:
        kind = _kind(n, graph.consts)
        if kind is None:
            continue
        limit, out = _RULES[kind]
        dyn = [i for i in n.input if i and i not in graph.consts]
        follow = []
        for d in dyn:
            st = ch.state.get(d)
            if st is None:  # a nonlinear node's output or a graph input: a source
                continue
            if st > limit or (st >= PROD and len(readers.get(d, ())) > 1):
                ch.cuts.add(d)  # computed here, a source from here on
            else:
                follow.append(d)
        states = [ch.state[d] for d in follow] or [SEL]
        st = max(states) if out is None else out
        if n.op_type == "Concat" and st == SEL and len(dyn) < len(n.input):
            st = SELC  # constants among the moved elements
        srcs = frozenset().union(*(ch.sources[d] if d in follow else {d} for d in dyn))
        ch.follow[id(n)] = follow
        for o in n.output:
            if o:
                ch.state[o], ch.sources[o], ch.producer[o] = st, srcs, n
    return ch


def _chain_nodes(ch: _Chains, end: str) -> list[onnx.NodeProto]:
    """The nodes computing ``end`` from its sources."""
    seen: dict[int, onnx.NodeProto] = {}
    todo = [ch.producer[end]]
    while todo:
        n = todo.pop()
        if id(n) not in seen:
            seen[id(n)] = n
            todo += [ch.producer[d] for d in ch.follow[id(n)]]
    return list(seen.values())


def _ends(graph: Graph, ch: _Chains) -> list[str]:
    """Affine tensors that something other than an affine chain reads (or that are cut)."""
    readers = graph.consumers()
    outputs = {o.name for o in graph.outputs}
    ends = []
    for t in ch.state:
        read_by_chain = all(
            id(r) in ch.follow and t in ch.follow[id(r)] for r in readers.get(t, ())
        )
        if t in outputs or t in ch.cuts or not read_by_chain:
            ends.append(t)
    return ends


@dataclass
class _Fold:
    """One chain to fold: its end, its sources (in order), its nodes, ``y = M x + c``."""

    end: str
    sources: list[str]
    nodes: list[onnx.NodeProto]
    M: np.ndarray | None = None  # (sum of source sizes, end size)
    c: np.ndarray | None = None  # (end size,)


def _candidates(graph: Graph, ch: _Chains) -> list[_Fold]:
    """The chains that may be worth folding: float32 ends and sources of static shape."""
    rank = {i.name: k for k, i in enumerate(graph.inputs)}
    for k, n in enumerate(graph.nodes):
        rank.update({o: len(rank) + k for o in n.output})
    folds = []
    for t in _ends(graph, ch):
        srcs = sorted(ch.sources[t], key=lambda s: rank.get(s, -1))
        names = [*srcs, t]
        if any(graph.shape(s) is None or graph.info(s)[1] != TensorProto.FLOAT for s in names):
            continue
        if sum(int(np.prod(graph.shape(s) or ())) for s in srcs) <= 1024:
            folds.append(_Fold(t, srcs, _chain_nodes(ch, t)))
    return [f for f in folds if len(f.nodes) > 1]


def _measure(graph: Graph, folds: list[_Fold]) -> None:
    """Set each fold's ``M`` and ``c`` by running the chains in float64 on unit probes."""
    groups: list[list[_Fold]] = []
    for f in folds:
        g = groups[-1] if groups else None
        made = {o for h in g or () for n in h.nodes for o in n.output}
        if (
            g is None
            or set(f.sources) & made
            or {o for n in f.nodes for o in n.output} & {s for h in g for s in h.sources}
        ):
            groups.append([f])
        else:
            g.append(f)
    wide = {k: v.astype(np.float64) for k, v in graph.consts.items() if v.dtype == np.float32}
    for group in groups:
        _measure_group(graph, group, wide)


def _measure_group(graph: Graph, folds: list[_Fold], wide: dict[str, np.ndarray]) -> None:
    chain = {id(n): n for f in folds for n in f.nodes}
    nodes = [n for n in graph.nodes if id(n) in chain]
    sources = sorted({s for f in folds for s in f.sources})
    zero = {s: np.zeros(graph.shape(s) or ()) for s in sources}
    probes: list[dict[str, np.ndarray]] = [zero]
    for s in sources:
        for j in range(zero[s].size):
            unit = np.zeros(zero[s].size)
            unit[j] = 1.0
            probes.append({**zero, s: unit.reshape(zero[s].shape)})
    ends = [f.end for f in folds]
    values = run_subgraph(graph, nodes, probes, ends, wide, TensorProto.DOUBLE)
    runs = [[y.reshape(-1) for y in ys] for ys in values]
    offset = np.cumsum([1] + [zero[s].size for s in sources])
    for k, f in enumerate(folds):
        base = runs[0][k]
        cols = [
            runs[offset[sources.index(s)] + j][k] - base
            for s in f.sources
            for j in range(zero[s].size)
        ]
        f.M, f.c = np.stack(cols), base


def _row_map(graph: Graph, f: _Fold) -> tuple[np.ndarray, np.ndarray] | None:
    """One row's map ``W`` and the offsets ``C``, if the chain maps every row alike."""
    assert f.M is not None and f.c is not None
    out = graph.shape(f.end) or ()
    rows = int(np.prod(out[:-1]))
    sizes = [int(np.prod(graph.shape(s) or ())) for s in f.sources]
    if rows < 2 or any(size % rows for size in sizes):
        return None
    blocks, at, diagonal = [], 0, np.arange(rows)
    for size in sizes:
        block = f.M[at : at + size].reshape(rows, size // rows, rows, out[-1])
        at += size
        diag = block[diagonal, :, diagonal]  # (rows, width, end width)
        off = block.copy()
        off[diagonal, :, diagonal] = 0.0
        if np.any(off) or np.any(diag != diag[0]):
            return None
        blocks.append(diag[0])
    return np.concatenate(blocks), f.c.reshape(rows, out[-1])


class _Emitter:
    """New nodes for folded chains (:meth:`plan`, :meth:`accept`); shared layouts made once."""

    def __init__(self, graph: Graph) -> None:
        self.graph = graph
        self.nodes: list[onnx.NodeProto] = []
        self._made: dict[tuple, str] = {}  # (kind, inputs, layout) -> tensor, accepted
        self._new: dict[tuple, str] = {}  # the same, of the current plan

    def _layout(self, key: tuple, op: str, ins: list[str], out: str, new: list, **kw) -> str:
        if key in self._made or key in self._new:
            return self._made.get(key) or self._new[key]
        new.append(helper.make_node(op, ins, [out], **kw))
        self._new[key] = out
        return out

    def _reshape(self, name: str, shape: tuple[int, ...], new: list) -> str:
        if self.graph.shape(name) == shape:
            return name
        out = f"{name}/as{'x'.join(map(str, shape))}"
        self.graph.consts[out + "/shape"] = np.array(shape, np.int64)
        return self._layout(("reshape", name, shape), "Reshape", [name, out + "/shape"], out, new)

    def _concat(self, names: list[str], axis: int, new: list) -> str:
        if len(names) == 1:
            return names[0]
        out = f"{names[0]}/cat{len(names)}_{len(self._made) + len(self._new)}"
        return self._layout(("concat", tuple(names), axis), "Concat", names, out, new, axis=axis)

    def plan(self, f: _Fold) -> list[onnx.NodeProto] | None:
        """The nodes computing ``f.end`` from its sources (None: no folded form fits)."""
        assert f.M is not None and f.c is not None
        g, out, new = self.graph, self.graph.shape(f.end) or (), []
        self._new = {}
        rowwise = _row_map(g, f)
        identity = not np.any(f.c) and np.array_equal(f.M, np.eye(len(f.M)))  # y = x
        if len(f.sources) == 1 and identity:
            self.graph.consts[f.end + "/shape"] = np.array(out, np.int64)
            new.append(helper.make_node("Reshape", [f.sources[0], f.end + "/shape"], [f.end]))
        elif rowwise is not None:
            W, C = rowwise
            rows = int(np.prod(out[:-1]))
            widths = [int(np.prod(g.shape(s) or ())) // rows for s in f.sources]
            parts = [
                self._reshape(s, (rows, k), new) for s, k in zip(f.sources, widths, strict=True)
            ]
            x = self._concat(parts, 1, new)
            bias = C[0] if np.all(C == C[0]) else C
            self._gemm(f.end, x, W, bias, (rows, W.shape[1]), new)
        elif f.M.size <= MAX_ENTRIES:
            flat = [self._reshape(s, (1, int(np.prod(g.shape(s) or ()))), new) for s in f.sources]
            self._gemm(f.end, self._concat(flat, 1, new), f.M, f.c, (1, f.M.shape[1]), new)
        else:
            return None
        return new

    def accept(self, new: list[onnx.NodeProto]) -> None:
        """Keep the last plan's nodes."""
        self.nodes += new
        self._made.update(self._new)

    def _gemm(self, end: str, x: str, W: np.ndarray, bias: np.ndarray, shape, new) -> None:
        """``end = x W + bias`` (``x W`` of shape ``shape``, reshaped to ``end``'s shape)."""
        out = self.graph.shape(end)
        moves = np.all((W == 1) | (W == 0)) and np.all(W.sum(0) == 1) and not np.any(bias)
        idx = np.argmax(W, axis=0).astype(np.int64)
        if moves and W.shape[0] == W.shape[1] and np.all(idx == np.arange(idx.size)):
            y = x  # the sources, laid out as they are
        elif moves:  # a selection of source elements
            y, self.graph.consts[end + "/idx"] = end + "/gathered", idx
            new.append(helper.make_node("Gather", [x, end + "/idx"], [y], axis=1))
        else:
            y = end + "/gemm"
            self.graph.consts[end + "/W"] = W.astype(np.float32)
            self.graph.consts[end + "/c"] = np.asarray(bias, np.float32)
            new.append(helper.make_node("Gemm", [x, end + "/W", end + "/c"], [y]))
        if out == shape and new and new[-1].output[0] == y:
            new[-1].output[0] = end
        else:
            self.graph.consts[end + "/shape"] = np.array(out, np.int64)
            new.append(helper.make_node("Reshape", [y, end + "/shape"], [end]))


def _cost(graph: Graph, nodes: list[onnx.NodeProto]) -> int:
    """How many nodes ONNX Runtime runs for ``nodes`` (a MatMul of a 3-d tensor is three)."""
    wide = [n for n in nodes if n.op_type == "MatMul" and len(graph.shape(n.input[0]) or ()) > 2]
    return len(nodes) + 2 * len(wide)


def fold_affine(graph: Graph) -> Graph:
    """Fold the graph's affine chains into ``Gemm`` nodes where that leaves fewer nodes."""
    graph.infer()
    folds = _candidates(graph, _chains(graph))
    _measure(graph, folds)
    emit = _Emitter(graph)
    folded: set[str] = set()
    for f in folds:
        new = emit.plan(f)
        if new is not None and len(new) < _cost(graph, f.nodes):
            emit.accept(new)
            folded.add(f.end)
    for n in graph.nodes:  # the old chains' ends are no longer theirs to compute
        n.output[:] = [f"{o}/unfolded" if o in folded else o for o in n.output]
    graph.nodes += emit.nodes
    graph.sort()
    return prune(graph)
