"""The ONNX Runtime backend: one session for any batch, and a fast one per plant at batch 1.

:class:`OnnxBackend` runs raw windows through the policy exported with a dynamic batch axis
(``backend(state, mask, ref, tag)``, as every backend does). For one plant stepped alone,
:meth:`OnnxBackend.single` gives a :class:`SingleRun`: a graph for that plant at batch 1,
run with its inputs and output bound once to the runtime's own arrays (no conversion, no
allocation, no dictionary per call). The graph is written from the weights where the
network allows (:mod:`~generalist_control.deploy.onnx_plant`: the paper's network and the
default); otherwise it is the policy exported for one row, its tag and mask (which a running
plant never changes) made constants and the graph shrunk by
:mod:`~generalist_control.deploy.onnx_graph` and :mod:`~generalist_control.deploy.onnx_affine`.
A step through it is mostly the network's arithmetic instead of ONNX Runtime's per-node and
per-call overhead (benchmarks/bench_latency.py).

Before a plant's graph is used it is checked against the general session on windows of the
plant's range: it must agree within :data:`AGREEMENT` (relative to the largest control), or
the next graph is tried (the written one, the shrunk one), and at last the plant is run
through the general session (and a warning says so).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
import onnx

from generalist_control.deploy.onnx_affine import fold_affine
from generalist_control.deploy.onnx_graph import (
    Graph,
    drop_trivial,
    einsum_to_matmul,
    fold_constants,
    freeze,
    prune,
)
from generalist_control.deploy.onnx_layout import tidy_reshapes

__all__ = ["AGREEMENT", "OnnxBackend", "SingleRun", "session", "shrink"]

#: ONNX Runtime's rewrites left out of a plant's graph: MatMulAddFusion makes a MatMul and
#: the Add of a computed tensor that follows it one Gemm, which sums in another order, and
#: MatMulScaleFusion a MatMul and a product by a constant that follows it one scaled MatMul
#: (the plant's control scale, a constant only in the plant's graph), which rounds once
#: less; the plant's graph is to give the general session's floats (its products and sums
#: are already the Gemms the general session's own fusion makes, onnx_affine).
_UNFUSED = ["MatMulAddFusion", "MatMulScaleFusion"]

#: Largest difference between a plant's graph and the general session, relative to the
#: largest control of a window, for the plant's graph to be used.
AGREEMENT = 1e-6


def session(model: bytes, arena: bool = True, disabled: list[str] | None = None) -> Any:
    """An ONNX Runtime session for one real-time thread.

    One intra- and one inter-op thread, sequential execution, all graph optimisations
    but those named in ``disabled``; ``arena``: ONNX Runtime's memory arena (of use where
    shapes change from call to call; for one static graph, whose buffers are planned once,
    a call is faster without it).
    """
    import onnxruntime as ort  # optional and heavy: only for the ONNX backend

    opts = ort.SessionOptions()
    opts.enable_cpu_mem_arena = arena
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3  # warnings of the optimiser are not the user's business
    return ort.InferenceSession(
        model, opts, providers=["CPUExecutionProvider"], disabled_optimizers=disabled
    )


def shrink(model: onnx.ModelProto, fixed: dict[str, np.ndarray], keep: list[str]) -> bytes:
    """The batch-1 graph with inputs ``fixed`` made constants, computing only ``keep``."""
    graph = freeze(Graph.from_model(model), fixed)
    graph.outputs = [o for o in graph.outputs if o.name in keep]
    graph = fold_constants(prune(drop_trivial(fold_constants(graph))))
    graph = tidy_reshapes(fold_affine(prune(einsum_to_matmul(graph))))
    return prune(fold_constants(graph)).to_model().SerializeToString()  # reshaped constants


class SingleRun:
    """The policy for one plant at batch 1: ``run(state, ref) -> controls (1, horizon)``.

    ``state`` (1, history, width) and ``ref`` (1, history) float32 C-contiguous arrays are
    read in place, as views of the shapes the session's inputs declare (e.g. without the
    batch axis); the controls are written to one float32 array, returned by every call
    (copy what must outlive the next call). Bindings to the arrays of the last few windows
    are kept, so a window builder that alternates between two arrays costs no binding.
    ``fixed``: the session's other inputs (e.g. the mask and tag of a general session).
    """

    def __init__(
        self, sess: Any, horizon: int, fixed: dict[str, np.ndarray] | None = None
    ) -> None:
        import onnxruntime as ort  # optional and heavy: only for the ONNX backend

        self._ort, self._sess = ort, sess
        self._fixed = {k: ort.OrtValue.ortvalue_from_numpy(v) for k, v in (fixed or {}).items()}
        self.out = np.zeros((1, horizon), np.float32)
        self._out = ort.OrtValue.ortvalue_from_numpy(self.out)
        self._bound: dict[tuple[int, int], tuple] = {}
        self._shapes = {
            i.name: tuple(i.shape)
            for i in sess.get_inputs()
            if all(isinstance(d, int) for d in i.shape)
        }
        # the session's own run of a binding, without the Python wrapper's per-call checks
        # (of a WebGPU graph capture, which a CPU session never has)
        inner = getattr(sess, "_sess", None)
        self._raw = getattr(inner, "run_with_iobinding", None)

    def _bind(self, state: np.ndarray, ref: np.ndarray) -> tuple:
        if not (state.flags.c_contiguous and ref.flags.c_contiguous):
            raise ValueError("the batch-1 session reads C-contiguous float32 windows")
        if len(self._bound) >= 4:  # windows of an earlier buffer: let them go
            self._bound.clear()
        b = self._sess.io_binding()
        views = []
        for name, array in (("state", state), ("ref", ref)):
            shape = self._shapes.get(name, array.shape)
            views.append(array.reshape(shape))  # a view: the array is C-contiguous
            b.bind_ortvalue_input(name, self._ort.OrtValue.ortvalue_from_numpy(views[-1]))
        for name, value in self._fixed.items():
            b.bind_ortvalue_input(name, value)
        b.bind_ortvalue_output("controls", self._out)
        raw = getattr(b, "_iobinding", None)
        entry = (b, raw if self._raw is not None and raw is not None else None, state, ref, views)
        self._bound[id(state), id(ref)] = entry  # the arrays and views kept alive with it
        return entry

    def __call__(self, state: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Controls (1, horizon) in plant units for one window (see the class docstring)."""
        entry = self._bound.get((id(state), id(ref))) or self._bind(state, ref)
        if entry[1] is not None and self._raw is not None:
            self._raw(entry[1], None)
        else:
            self._sess.run_with_iobinding(entry[0])
        return self.out


class OnnxBackend:
    """``backend(state, mask, ref, tag) -> controls`` through ONNX Runtime, any batch size.

    Parameters
    ----------
    general : bytes
        The policy exported with a dynamic batch axis (inputs state, mask, ref, tag).
    batch_one : callable
        Returns the policy exported for one row (static shapes), when first needed.
    horizon : int
    plant_graph : callable, optional
        ``plant_graph(tag, mask)``: a plant's batch-1 graph written from the weights, or
        None where the network is not one it writes
        (:func:`~generalist_control.deploy.onnx_plant.plant_graph`).
    """

    def __init__(
        self, general: bytes, batch_one: Any, horizon: int, plant_graph: Any = None
    ) -> None:
        self._sess = session(general)
        self._batch_one = batch_one
        self._plant_graph = plant_graph
        self._one_model: onnx.ModelProto | None = None
        self.horizon = horizon
        self._single: dict[tuple[int, bytes], SingleRun] = {}

    def __call__(
        self, state: np.ndarray, mask: np.ndarray, ref: np.ndarray, tag: np.ndarray
    ) -> np.ndarray:
        """Controls (B, horizon) of raw windows, through the general session."""
        feeds = {"state": state, "mask": mask, "ref": ref, "tag": tag}
        return self._sess.run(["controls"], feeds)[0]

    def single(self, tag: int, mask: np.ndarray) -> SingleRun:
        """The batch-1 run of plant ``tag`` whose windows have mask ``mask`` (1, T, width).

        Built once per plant (milliseconds written, 0.1 s shrunk) and checked against the
        general session (module docstring); a plant whose graphs all disagree is run through
        the general session.
        """
        mask = np.ascontiguousarray(mask, np.float32)
        key = (int(tag), mask.tobytes())
        if key not in self._single:
            fixed = {"tag": np.array([tag], np.int64), "mask": mask}
            worst = 0.0
            for graph in self._graphs(tag, mask, fixed):
                run = SingleRun(session(graph, arena=False, disabled=_UNFUSED), self.horizon)
                worst = self._disagreement(run, fixed)
                if worst <= AGREEMENT:
                    self._single[key] = run
                    return run
            warnings.warn(
                f"the batch-1 ONNX graph of tag {tag} differs from the general session by "
                f"{worst:.3g} (relative; allowed {AGREEMENT:g}): this plant runs through the "
                "general session instead, which is slower. Please report this with the "
                "policy file.",
                RuntimeWarning,
                stacklevel=2,
            )
            self._single[key] = SingleRun(self._sess, self.horizon, fixed)
        return self._single[key]

    def _graphs(self, tag: int, mask: np.ndarray, fixed: dict[str, np.ndarray]) -> Iterator[bytes]:
        """The plant's batch-1 graphs to try, fastest first: written, then shrunk."""
        written = self._plant_graph(tag, mask) if self._plant_graph is not None else None
        if written is not None:
            yield written
        self._one_model = self._one_model or onnx.load_from_string(self._batch_one())
        yield shrink(self._one_model, fixed, ["controls"])

    def _disagreement(self, run: SingleRun, fixed: dict[str, np.ndarray]) -> float:
        """Largest relative difference of ``run`` to the general session on random windows."""
        mask, tag = fixed["mask"], fixed["tag"]
        rng = np.random.default_rng(0)
        worst = 0.0
        for scale in (1e-3, 1e-1, 1.0, 10.0, 1e3):
            state = (rng.normal(size=mask.shape) * scale).astype(np.float32) * mask
            ref = (rng.normal(size=mask.shape[:2]) * scale).astype(np.float32)
            a = self(state, mask, ref, tag)
            b = run(state, ref)
            worst = max(worst, float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-30)))
        return worst
