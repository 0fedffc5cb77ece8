"""Backends of a trained policy (eager PyTorch, ONNX Runtime) and its ONNX export.

A backend maps raw float32 windows to the ``horizon`` controls in plant units; with ONNX
Runtime one plant stepped alone runs a shrunk batch-1 graph of its own (:func:`plant_model`).
"""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch

from generalist_control.deploy.onnx_affine import fold_affine
from generalist_control.deploy.onnx_graph import (
    Graph,
    einsum_to_matmul,
    fold_constants,
    freeze,
    prune,
    session,
    tidy_reshapes,
)
from generalist_control.model.policy import Policy

__all__ = ["BACKENDS", "Backend", "backend", "export_onnx", "onnx_bytes"]

_INPUTS = ("state", "mask", "ref", "tag")
#: The backends :func:`backend` builds.
BACKENDS = ("torch", "onnx")

PlantRun = Callable[[np.ndarray, np.ndarray], np.ndarray]


class Backend:
    """The policy in eager PyTorch: ``backend(state, mask, ref, tag) -> controls``."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy

    @torch.inference_mode()
    def __call__(
        self, state: np.ndarray, mask: np.ndarray, ref: np.ndarray, tag: np.ndarray
    ) -> np.ndarray:
        """Controls (B, horizon) in plant units for raw windows."""
        arrays = (state, mask, ref, tag)
        return self.policy(*(torch.from_numpy(a) for a in arrays))[0].numpy()

    def plant(self, tag: int, mask: np.ndarray) -> PlantRun:
        """``run(state, ref) -> controls (1, horizon)`` of plant ``tag`` (mask (1, T, width))."""
        tags = np.array([tag], np.int64)
        return lambda state, ref: self(state, mask, ref, tags)


def _example(policy: Policy, batch: int = 2) -> tuple[torch.Tensor, ...]:
    T, n = policy.history, policy.width
    return (
        torch.zeros(batch, T, n),
        torch.ones(batch, T, n),
        torch.zeros(batch, T),
        torch.zeros(batch, dtype=torch.long),
    )


def onnx_bytes(policy: Policy, batch: int | None = None) -> bytes:
    """``policy`` as an ONNX model; ``batch``: None for a dynamic batch axis, else fixed."""
    dyn = None if batch else {k: {0: "batch"} for k in (*_INPUTS, "controls", "gates")}
    buffer = io.BytesIO()
    with torch.no_grad():
        torch.onnx.export(
            policy.eval(),
            _example(policy, batch or 2),
            buffer,  # type: ignore[arg-type]  # the TorchScript-based exporter writes to it
            input_names=list(_INPUTS),
            output_names=["controls", "gates"],
            dynamic_axes=dyn,
            opset_version=17,
            dynamo=False,
        )
    return buffer.getvalue()


def export_onnx(policy: Policy, path: str | Path) -> Path:
    """Export ``policy`` to ONNX with a dynamic batch axis (inputs state, mask, ref, tag)."""
    path = Path(path)
    path.write_bytes(onnx_bytes(policy))
    return path


#: ONNX Runtime's rewrites left out of a plant's session, which would not compute the batch
#: session's floats: MatMulAddFusion sums a product and a computed tensor in another order,
#: MatMulScaleFusion folds the plant's control scale (a constant there) into a product.
_UNFUSED = ("MatMulAddFusion", "MatMulScaleFusion")


def plant_model(batch_one: onnx.ModelProto, fixed: dict[str, np.ndarray]) -> bytes:
    """The batch-1 model with inputs ``fixed`` made constants and shrunk; ``controls`` out.

    The rewrites (:mod:`~generalist_control.deploy.onnx_graph`,
    :mod:`~generalist_control.deploy.onnx_affine`) compute the batch session's floats.
    """
    graph = freeze(Graph.from_model(batch_one), fixed)
    graph.outputs = [o for o in graph.outputs if o.name == "controls"]
    graph = prune(fold_constants(graph))
    graph = tidy_reshapes(fold_affine(prune(einsum_to_matmul(graph))))
    return prune(fold_constants(graph)).to_model().SerializeToString()


class _BoundRun:
    """A plant's batch-1 session bound to the window's arrays (two sets, so two bindings)."""

    def __init__(self, sess: Any, horizon: int) -> None:
        import onnxruntime as ort  # optional and heavy: only for the ONNX backend

        self._value, self._sess = ort.OrtValue.ortvalue_from_numpy, sess
        self.out = np.zeros((1, horizon), np.float32)
        self._bound: dict[tuple[int, int], tuple[Any, np.ndarray, np.ndarray]] = {}

    def _bind(self, state: np.ndarray, ref: np.ndarray) -> Any:
        if len(self._bound) >= 2:  # arrays of an earlier buffer: let them go
            self._bound.clear()
        binding = self._sess.io_binding()
        binding.bind_ortvalue_input("state", self._value(state))
        binding.bind_ortvalue_input("ref", self._value(ref))
        binding.bind_ortvalue_output("controls", self._value(self.out))
        self._bound[id(state), id(ref)] = (binding, state, ref)  # the arrays kept alive
        return binding

    def __call__(self, state: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Controls (1, horizon) for a C-contiguous float32 window (1, T, width), (1, T)."""
        bound = self._bound.get((id(state), id(ref)))
        self._sess.run_with_iobinding(bound[0] if bound else self._bind(state, ref))
        return self.out


class OnnxBackend(Backend):
    """The policy through ONNX Runtime: one session for any batch, one per plant at batch 1."""

    def __init__(self, policy: Policy) -> None:
        super().__init__(policy)
        self._sess = session(onnx_bytes(policy))
        self._batch_one: onnx.ModelProto | None = None
        self._plants: dict[tuple[int, bytes], _BoundRun] = {}

    def __call__(
        self, state: np.ndarray, mask: np.ndarray, ref: np.ndarray, tag: np.ndarray
    ) -> np.ndarray:
        """Controls (B, horizon) in plant units for raw windows."""
        feeds = {"state": state, "mask": mask, "ref": ref, "tag": tag}
        return self._sess.run(["controls"], feeds)[0]

    def plant(self, tag: int, mask: np.ndarray) -> PlantRun:
        """Plant ``tag``'s batch-1 session (:func:`plant_model`), made at its first use."""
        mask = np.ascontiguousarray(mask, np.float32)
        key = (int(tag), mask.tobytes())
        if key not in self._plants:
            if self._batch_one is None:
                self._batch_one = onnx.load_from_string(onnx_bytes(self.policy, batch=1))
            fixed = {"tag": np.array([tag], np.int64), "mask": mask}
            sess = session(plant_model(self._batch_one, fixed), arena=False, disabled=_UNFUSED)
            self._plants[key] = _BoundRun(sess, self.policy.horizon)
        return self._plants[key]


def backend(policy: Policy, name: str) -> Backend:
    """Backend ``name`` (torch or onnx) of ``policy``."""
    if name not in BACKENDS:
        raise ValueError(f"unknown backend '{name}'; choose one of {', '.join(BACKENDS)}")
    return OnnxBackend(policy) if name == "onnx" else Backend(policy)
