"""The batch-1 ONNX graph of one plant, written from the policy's weights.

For a policy whose plant reaches the network through its tag's embedding row (the paper's
network and the default: :class:`~generalist_control.model.plant.TagEmbedding`, no per-tag
table, at most a one-sample :class:`~generalist_control.model.linear.LinearSkip`),
:func:`plant_graph` writes the graph that steps one plant at batch 1 directly, in a quarter
of the exported graph's nodes (two thirds of those of the exported graph shrunk by
:func:`~generalist_control.deploy.onnx_backend.shrink`). Each node costs ONNX Runtime
about half a microsecond a call whatever its size, so the count is most of a step.

The graph computes the general session's floats bit for bit (and is used only where it
does, :meth:`~generalist_control.deploy.onnx_backend.OnnxBackend.single`): every product and
sum is the same kernel on the same numbers in the same order. Constants that depend on the
plant only (its encoder's features, its skip gains) are computed by ONNX Runtime as the
general session computes them; zero blocks added to a product (three encoders as one matrix,
the window's floor as an extra column) add exact zeros. What is joined:

* the state, reference and a constant column ``1e-3`` (the window scale's floor) are one
  ``(history, width + 2)`` matrix, divided by the normaliser's scales (``inf`` where the
  mask is zero), so one ``ReduceMax`` gives the window scale;
* the three encoders' first layers are one product, their second layers another (block
  diagonal, the plant's features in its bias);
* the three experts' first layers are one product.

Its inputs are ``state`` (history, width) and ``ref`` (history, 1): the window builder's
arrays viewed without their batch axis (:class:`~generalist_control.deploy.onnx_backend.SingleRun`
binds views of the shapes a graph declares).
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper
from torch import nn

from generalist_control.model.linear import LinearSkip
from generalist_control.model.network import WINDOW_SCALE_FLOOR, GeneralistNetwork
from generalist_control.model.plant import TagEmbedding
from generalist_control.model.policy import Policy

__all__ = ["plant_graph", "supported"]

#: The opset of the written graph (that of the exported one, deploy/export.py).
OPSET = 17


def supported(net: GeneralistNetwork) -> bool:
    """Whether :func:`plant_graph` can write ``net``'s graph (the module docstring)."""
    skip = net.skip
    return (
        type(net.plant) is TagEmbedding
        and (skip is None or (type(skip) is LinearSkip and skip.samples == 1))
        and "previous_control" not in net.channels
        and net.law_history == net.history
    )


def _array(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().float().numpy()


def _gemm(x: np.ndarray, layer: nn.Linear) -> np.ndarray:
    """``layer(x)`` for one row, computed by ONNX Runtime as the exported graph's Gemm."""
    import onnxruntime as ort  # optional and heavy: only for the ONNX backend

    w, b = _array(layer.weight), _array(layer.bias)
    node = helper.make_node("Gemm", ["x", "w", "b"], ["y"], transB=1)
    graph = helper.make_graph(
        [node],
        "linear",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(x.shape))],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
        [numpy_helper.from_array(w, "w"), numpy_helper.from_array(b, "b")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(model.SerializeToString(), opts, ["CPUExecutionProvider"])
    return np.asarray(sess.run(["y"], {"x": np.ascontiguousarray(x, np.float32)})[0])


class _Writer:
    """Nodes and constants of a graph being written; names made unique by a counter."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.consts: list[onnx.TensorProto] = []

    def const(self, value: Any, dtype: Any = np.float32) -> str:
        """A constant of ``value``; its name."""
        name = f"c{len(self.consts)}"
        self.consts.append(numpy_helper.from_array(np.ascontiguousarray(value, dtype), name))
        return name

    def shape(self, *dims: int) -> str:
        """An int64 constant of ``dims`` (a shape, or Slice's starts, ends, axes, steps)."""
        return self.const(np.array(dims), np.int64)

    def op(self, op: str, *inputs: str, outputs: int = 1, name: str | None = None,
           **attrs: Any) -> Any:  # fmt: skip
        """A node ``op`` of ``inputs``; its output's name (a list for several)."""
        n = len(self.nodes)
        outs = [name] if name else [f"{op}{n}_{i}" for i in range(outputs)]
        self.nodes.append(helper.make_node(op, list(inputs), outs, **attrs))
        return outs[0] if outputs == 1 else outs

    def gemm(self, x: str, w: np.ndarray, b: np.ndarray) -> str:
        """``x @ w + b`` (w: in x out)."""
        return self.op("Gemm", x, self.const(w), self.const(b))

    def model(self, net: GeneralistNetwork) -> bytes:
        """The serialised model: inputs state (T, width) and ref (T, 1), output controls."""
        T = net.history
        graph = helper.make_graph(
            self.nodes,
            "plant",
            [helper.make_tensor_value_info("state", TensorProto.FLOAT, [T, net.width]),
             helper.make_tensor_value_info("ref", TensorProto.FLOAT, [T, 1])],
            [helper.make_tensor_value_info("controls", TensorProto.FLOAT, [1, net.horizon])],
            self.consts,
        )  # fmt: skip
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
        model.ir_version = 8
        return model.SerializeToString()


def _lstm(g: _Writer, lstm: Any, x: str) -> str:
    """The LSTM's final hidden state (1, 1, hidden) over ``x`` (steps, 1, input)."""
    h = lstm.hidden_size

    def iofc(a: np.ndarray) -> np.ndarray:  # PyTorch's gate order i f g o, ONNX's i o f c
        return np.concatenate([a[:h], a[3 * h :], a[h : 2 * h], a[2 * h : 3 * h]])

    w = iofc(_array(lstm.weight_ih_l0))[None]
    r = iofc(_array(lstm.weight_hh_l0))[None]
    b = np.concatenate([iofc(_array(lstm.bias_ih_l0)), iofc(_array(lstm.bias_hh_l0))])[None]
    _, y_h, _ = g.op("LSTM", x, g.const(w), g.const(r), g.const(b), outputs=3, hidden_size=h)
    return str(y_h)


def _encoded(g: _Writer, net: GeneralistNetwork, n: str, code: np.ndarray) -> str:
    """The LSTMs' input (history, 1, 4 e): the three encoders and the plant's features."""
    encoders: tuple[Any, ...] = (net.state_encoder_1, net.state_encoder_2, net.ref_encoder)
    d, e, width = encoders[0][0].out_features, encoders[0][2].out_features, net.width
    w1 = np.zeros((width + 1 + net.window_scale, 3 * d), np.float32)
    b1 = np.zeros(3 * d, np.float32)
    w2, b2 = np.zeros((3 * d, 4 * e), np.float32), np.zeros(4 * e, np.float32)
    rows = (slice(0, width), slice(0, width), slice(width, width + 1))  # [x; z], r
    for i, (enc, x) in enumerate(zip(encoders, rows, strict=True)):
        w1[x, i * d : (i + 1) * d] = _array(enc[0].weight).T
        b1[i * d : (i + 1) * d] = _array(enc[0].bias)
        w2[i * d : (i + 1) * d, i * e : (i + 1) * e] = _array(enc[2].weight).T
        b2[i * e : (i + 1) * e] = _array(enc[2].bias)
    plant_encoder: Any = net.plant_encoder
    b2[3 * e :] = _gemm(np.maximum(code, 0.0), plant_encoder[1])[0]  # ReLU then Linear
    h = g.op("Relu", g.gemm(n, w1, b1))
    return g.op("Reshape", g.gemm(h, w2, b2), g.shape(net.history, 1, 4 * e))


def _experts(g: _Writer, net: GeneralistNetwork, z: str) -> str:
    """The experts' controls (M, horizon) for the summary ``z`` (1, 2 d)."""
    experts: list[Any] = list(net.experts)
    d, k = experts[0][0].out_features, net.horizon
    w = np.concatenate([_array(x[0].weight).T for x in experts], 1)
    b = np.concatenate([_array(x[0].bias) for x in experts])
    first = g.op("Relu", g.gemm(z, w, b))
    parts = g.op("Split", first, g.shape(*[d] * len(experts)), outputs=len(experts), axis=1)
    outs = []
    for part, x in zip(parts, experts, strict=True):
        a = g.op("LayerNormalization", part, g.const(_array(x[2].weight)),
                 g.const(_array(x[2].bias)), axis=-1, epsilon=x[2].eps)  # fmt: skip
        a = g.op("Relu", g.gemm(a, _array(x[3].weight).T, _array(x[3].bias)))
        outs.append(g.op("LayerNormalization", a, g.const(_array(x[5].weight)),
                         g.const(_array(x[5].bias)), axis=-1, epsilon=x[5].eps))  # fmt: skip
    last = np.zeros((len(experts) * d, len(experts) * k), np.float32)
    for i, x in enumerate(experts):
        last[i * d : (i + 1) * d, i * k : (i + 1) * k] = _array(x[6].weight).T
    bias = np.concatenate([_array(x[6].bias) for x in experts])
    out = g.gemm(g.op("Concat", *outs, axis=1), last, bias)
    return g.op("Reshape", out, g.shape(len(experts), k))


def plant_graph(policy: Policy, tag: int, mask: np.ndarray) -> bytes | None:
    """The batch-1 graph of plant ``tag`` (module docstring), or None if not supported.

    Parameters
    ----------
    policy : Policy
    tag : int
        The plant's system tag.
    mask : ndarray, shape (1, history, width)
        The plant's window mask (:attr:`~generalist_control.data.windows.HistoryBuffer.mask`).

    Returns
    -------
    bytes or None
        A serialised ONNX model: inputs ``state`` (history, width) and ``ref`` (history, 1),
        output ``controls`` (1, horizon) in plant units.
    """
    net = policy.net
    if not supported(net):
        return None
    norm = policy.normaliser
    sx, sr, su = (_array(s)[tag] for s in (norm.state_scale, norm.ref_scale, norm.control_scale))
    code = _array(cast(TagEmbedding, net.plant).rows.weight)[tag : tag + 1]
    g = _Writer()
    v, s = _window(g, net, sx, sr, mask)
    x = _encoded(g, net, v, code)
    h_fast = _lstm(g, net.lstm_fast, x)
    slow = g.op("Slice", x, *(g.shape(i) for i in (net.slow_start, net.history, 0, net.stride)))
    h_slow = _lstm(g, net.lstm_slow, slow)
    z = g.op("Reshape", g.op("Concat", h_fast, h_slow, axis=2), g.shape(1, -1))
    att, inner = net.attention, net.attention.heads * net.attention.d_k
    wv, bv = _array(att.qkv.weight)[2 * inner :], _array(att.qkv.bias)[2 * inner :]
    out = g.gemm(g.gemm(z, wv.T, bv), _array(att.out.weight).T, _array(att.out.bias))
    z_att = g.op("Add", z, out)
    gates = g.op("Softmax", g.gemm(z_att, _array(net.gate.weight).T, _array(net.gate.bias)),
                 axis=-1)  # fmt: skip
    u = g.op("MatMul", gates, _experts(g, net, z_att))
    if net.skip is not None:  # gains (horizon, width + 1) times the newest [x; z; r]
        width = net.width
        gains = _gemm(code, net.skip.gains).reshape(net.horizon, width + 1)
        newest = np.array([[[net.history - 1, j]] for j in range(width + 1)], np.int64)
        column = g.op("GatherND", v, g.const(newest, np.int64))
        # (K, F) x (F, 1) as the general session's einsum: (1, F) x (F, K) sums otherwise
        skip = g.op("MatMul", g.const(gains), column)
        u = g.op("Add", u, g.op("Reshape", skip, g.shape(1, net.horizon)))
    if s is not None:
        u = g.op("Mul", u, s)
    g.op("Mul", u, g.const(np.array(su)), name="controls")
    return g.model(net)


def _window(
    g: _Writer, net: GeneralistNetwork, sx: np.ndarray, sr: float, mask: np.ndarray
) -> tuple[str, str | None]:
    """The normalised window ``[x z r]`` (history, width + 1 or 2) and the window scale.

    ``x / s_x * mask`` as ``x / (s_x or inf)``, exactly; with window scaling a column of the
    scale's floor too, so that one ``ReduceMax`` gives the scale (None without).
    """
    T, width = net.history, net.width
    columns = ["state", "ref"]
    scales = [np.where(mask[0] > 0, sx[None, :width], np.inf), np.full((T, 1), sr)]
    if net.window_scale:
        columns.append(g.const(np.full((T, 1), WINDOW_SCALE_FLOOR)))
        scales.append(np.ones((T, 1)))
    v = g.op("Div", g.op("Concat", *columns, axis=1), g.const(np.concatenate(scales, 1)))
    if not net.window_scale:
        return v, None
    s = g.op("ReduceMax", g.op("Abs", v), keepdims=0)
    return g.op("Div", v, s), s
