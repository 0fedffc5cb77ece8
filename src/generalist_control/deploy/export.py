"""Export backends of a trained policy: eager PyTorch, TorchScript and ONNX Runtime.

Each backend is a function ``run(state, mask, ref, tag) -> controls`` on raw float32 windows
(the window builder's arrays) returning the ``horizon`` controls in plant units; the
:class:`~generalist_control.deploy.runtime.PolicyRuntime` calls it once per sample. Exports are
traced from the :class:`~generalist_control.model.policy.Policy` (normaliser included) with a
dynamic batch axis; their outputs equal PyTorch's within 1e-5 (tests/test_runtime.py).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from generalist_control.model.policy import Policy

__all__ = ["Backend", "backend", "export_onnx", "export_torchscript"]

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


def export_torchscript(policy: Policy, path: str | Path) -> Path:
    """Trace ``policy`` (raw windows in, ``(controls, gates)`` out) to a TorchScript file."""
    path = Path(path)
    with torch.no_grad():
        traced = torch.jit.trace(policy.eval(), _example(policy), check_trace=False)
    traced.save(str(path))
    return path


def export_onnx(policy: Policy, path: str | Path) -> Path:
    """Export ``policy`` to ONNX with a dynamic batch axis (inputs state, mask, ref, tag)."""
    path = Path(path)
    dyn = {k: {0: "batch"} for k in (*_INPUTS, "controls", "gates")}
    with torch.no_grad():
        torch.onnx.export(
            policy.eval(),
            _example(policy),
            str(path),
            input_names=list(_INPUTS),
            output_names=["controls", "gates"],
            dynamic_axes=dyn,
            opset_version=17,
            dynamo=False,
        )
    return path


def backend(policy: Policy, name: str) -> Backend:
    """The ``run(state, mask, ref, tag)`` function of backend ``name`` for ``policy``."""
    if name == "torch":
        return _torch_backend(policy)
    tmp = Path(tempfile.mkdtemp())
    if name == "torchscript":
        module = torch.jit.load(str(export_torchscript(policy, tmp / "policy.ts")))

        @torch.inference_mode()
        def run(state, mask, ref, tag):
            return module(*(torch.from_numpy(a) for a in (state, mask, ref, tag)))[0].numpy()

        return run
    if name == "onnx":
        import onnxruntime as ort  # optional and heavy: only for the ONNX backend

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        sess = ort.InferenceSession(str(export_onnx(policy, tmp / "policy.onnx")), opts)
        return lambda state, mask, ref, tag: sess.run(
            ["controls"], {"state": state, "mask": mask, "ref": ref, "tag": tag}
        )[0]
    raise ValueError(f"unknown backend '{name}'; choose torch, torchscript or onnx")
