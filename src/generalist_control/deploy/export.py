"""Export backends of a trained policy: eager PyTorch, TorchScript and ONNX Runtime.

Each backend is a function ``run(state, mask, ref, tag) -> controls`` on raw float32 windows
(the window builder's arrays) returning the ``horizon`` controls in plant units; the
:class:`~generalist_control.deploy.runtime.PolicyRuntime` calls it once per sample. Exports are
traced from the :class:`~generalist_control.model.policy.Policy` (normaliser included) with a
dynamic batch axis; their outputs equal PyTorch's within 1e-5 (tests/test_runtime.py). The
ONNX backend also runs one plant at batch 1 through a graph made for it
(:meth:`~generalist_control.deploy.onnx_backend.OnnxBackend.single`).

Backends are built in memory: nothing is written to disk (:func:`export_onnx` and
:func:`export_torchscript` write a file only where asked to).
"""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from generalist_control.deploy.onnx_backend import OnnxBackend
from generalist_control.deploy.onnx_plant import plant_graph
from generalist_control.model.policy import Policy

__all__ = ["Backend", "backend", "export_onnx", "export_torchscript", "onnx_bytes"]

_INPUTS = ("state", "mask", "ref", "tag")

Backend = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def _torch_backend(policy: Policy) -> Backend:
    @torch.inference_mode()
    def run(state, mask, ref, tag):
        u, _ = policy(*(torch.from_numpy(a) for a in (state, mask, ref, tag)))
        return u.numpy()

    return run


def _example(policy: Policy, batch: int = 2) -> tuple[torch.Tensor, ...]:
    T, n = policy.history, policy.width
    return (
        torch.zeros(batch, T, n),
        torch.ones(batch, T, n),
        torch.zeros(batch, T),
        torch.zeros(batch, dtype=torch.long),
    )


def _traced(policy: Policy) -> torch.jit.ScriptModule:
    with torch.no_grad():
        return torch.jit.trace(policy.eval(), _example(policy), check_trace=False)


def export_torchscript(policy: Policy, path: str | Path) -> Path:
    """Trace ``policy`` (raw windows in, ``(controls, gates)`` out) to a TorchScript file."""
    path = Path(path)
    _traced(policy).save(str(path))
    return path


def onnx_bytes(policy: Policy, batch: int | None = None) -> bytes:
    """``policy`` as an ONNX model (inputs state, mask, ref, tag; outputs controls, gates).

    ``batch``: None for a dynamic batch axis, or a fixed batch size (all shapes static).
    """
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


def backend(policy: Policy, name: str) -> Backend:
    """The ``run(state, mask, ref, tag)`` function of backend ``name`` for ``policy``."""
    if name == "torch":
        return _torch_backend(policy)
    if name == "torchscript":
        buffer = io.BytesIO()
        torch.jit.save(_traced(policy), buffer)
        buffer.seek(0)
        module = torch.jit.load(buffer)

        @torch.inference_mode()
        def run(state, mask, ref, tag):
            return module(*(torch.from_numpy(a) for a in (state, mask, ref, tag)))[0].numpy()

        return run
    if name == "onnx":
        return OnnxBackend(
            onnx_bytes(policy),
            lambda: onnx_bytes(policy, batch=1),
            policy.horizon,
            lambda tag, mask: plant_graph(policy, tag, mask),
        )
    raise ValueError(f"unknown backend '{name}'; choose torch, torchscript or onnx")
