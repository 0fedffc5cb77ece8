"""The real-time policy runtime: history buffer, receding horizon, export backends.

:class:`PolicyRuntime` wraps a trained :class:`~generalist_control.policy.Policy`. It keeps
its own ``history``-sample buffer of states and references, builds the network's input with
the project's one window builder (:class:`~generalist_control.windows.HistoryBuffer`),
and applies the first of the ``horizon`` predicted controls each sample::

    rt = PolicyRuntime.load("models/policy.ckpt")        # or an MLflow URI
    rt.reset("cstr")
    u = rt.step(x, r)                                     # once per dt

On the first step after ``reset`` the buffer is filled with that first sample, exactly as
the window builder pads the start of a training trajectory. Many plants can be stepped at
once (``reset([...names])`` and ``step`` on ``(B, MAX_ORDER)`` zero-padded states), which is
how evaluation batches all plants through one network call per sample.

Backends: ``"torch"`` (eager), ``"torchscript"`` and ``"onnx"`` (ONNX Runtime); see
:func:`export_torchscript` and :func:`export_onnx`.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from generalist_control.paths import TRAIN_COMMAND
from generalist_control.plants import MAX_ORDER
from generalist_control.policy import Policy, load_policy
from generalist_control.windows import HistoryBuffer

__all__ = ["PolicyController", "PolicyRuntime", "export_onnx", "export_torchscript", "resolve"]

POLICY_FILE = "policy.ckpt"
_INPUTS = ("state", "mask", "ref", "tag")

Backend = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def resolve(source: str | Path) -> Path:
    """A local policy file for a path or an MLflow URI (``runs:/...``, ``models:/...``).

    For an MLflow URI the run's ``policy/policy.ckpt`` artifact is downloaded (the plain
    tensor file, never the pickled MLflow model), so loading stays ``weights_only``.
    """
    text = str(source)
    if "://" not in text and not text.startswith(("runs:/", "models:/")):
        path = Path(text)
        if not path.is_file():
            raise FileNotFoundError(f"no policy at '{path}'. Train one with: {TRAIN_COMMAND}")
        return path
    import mlflow
    from mlflow.tracking import MlflowClient

    if text.startswith("models:/"):
        name, _, version = text[len("models:/") :].partition("/")
        mv = MlflowClient().get_model_version(name, version or "1")
        text = f"runs:/{mv.run_id}/policy/{POLICY_FILE}"
    elif text.startswith("runs:/") and "/" not in text[len("runs:/") :].strip("/"):
        text = text.rstrip("/") + "/policy"  # a bare run: its policy folder
    local = Path(
        mlflow.artifacts.download_artifacts(artifact_uri=text, dst_path=tempfile.mkdtemp())
    )
    if local.is_dir():
        found = sorted(local.rglob(POLICY_FILE))
        if not found:
            raise FileNotFoundError(f"no {POLICY_FILE} among the artifacts of '{source}'")
        local = found[0]
    return local


def _torch_backend(policy: Policy) -> Backend:
    @torch.inference_mode()
    def run(state, mask, ref, tag):
        u, _ = policy(*(torch.from_numpy(a) for a in (state, mask, ref, tag)))
        return u.numpy()

    return run


def _example(policy: Policy, batch: int = 2) -> tuple[torch.Tensor, ...]:
    c = policy.config
    T, n = c["history"], c["state_dim"]
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


def _backend(policy: Policy, backend: str) -> Backend:
    if backend == "torch":
        return _torch_backend(policy)
    tmp = Path(tempfile.mkdtemp())
    if backend == "torchscript":
        module = torch.jit.load(str(export_torchscript(policy, tmp / "policy.ts")))

        @torch.inference_mode()
        def run(state, mask, ref, tag):
            return module(*(torch.from_numpy(a) for a in (state, mask, ref, tag)))[0].numpy()

        return run
    if backend == "onnx":
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        sess = ort.InferenceSession(str(export_onnx(policy, tmp / "policy.onnx")), opts)
        return lambda state, mask, ref, tag: sess.run(
            ["controls"], {"state": state, "mask": mask, "ref": ref, "tag": tag}
        )[0]
    raise ValueError(f"unknown backend '{backend}'; choose torch, torchscript or onnx")


class PolicyRuntime:
    """A trained policy stepping one or many plants in a sampled loop.

    Parameters
    ----------
    policy : Policy
    meta : dict
        The policy's metadata: ``tags`` (plant -> tag), ``orders`` (plant -> order),
        ``history``, ``horizon``, ``dt``.
    backend : {"torch", "torchscript", "onnx"}
    """

    def __init__(self, policy: Policy, meta: dict[str, Any], backend: str = "torch") -> None:
        self.policy, self.meta = policy.eval(), meta
        self.tags: dict[str, int] = {str(k): int(v) for k, v in meta["tags"].items()}
        self.orders: dict[str, int] = {str(k): int(v) for k, v in meta["orders"].items()}
        self.history, self.horizon = int(meta["history"]), int(meta["horizon"])
        self.dt = float(meta["dt"])
        self.backend = backend
        self._run = _backend(policy, backend)
        self._systems: list[str] = []
        self._single = True
        self.plan = np.zeros((0, self.horizon), np.float32)

    @classmethod
    def load(cls, source: str | Path, backend: str = "torch") -> PolicyRuntime:
        """Load from a policy/checkpoint file or an MLflow URI (see :func:`resolve`)."""
        policy, meta = load_policy(resolve(source))
        return cls(policy, meta, backend)

    @property
    def systems(self) -> list[str]:
        """Plants known to the policy."""
        return sorted(self.tags)

    def reset(self, system: str | Sequence[str]) -> None:
        """Start a new run on ``system`` (a name) or a batch of runs (a list of names)."""
        self._single = isinstance(system, str)
        names = [system] if self._single else [str(s) for s in system]
        for name in names:
            if name not in self.tags:
                raise KeyError(
                    f"unknown plant '{name}' for this policy; it was trained on: "
                    f"{', '.join(self.systems)}"
                )
        self._systems = names
        self._tag = np.array([self.tags[s] for s in names], dtype=np.int64)
        self._order = np.array([self.orders[s] for s in names], dtype=np.int64)
        self._buffer = HistoryBuffer(self._order, self.history)
        self._padded = np.zeros((len(names), MAX_ORDER), np.float32)

    def _check(self, x: Any, r: Any) -> tuple[np.ndarray, np.ndarray]:
        if not self._systems:
            raise RuntimeError("call reset(system) before step(x, r)")
        x = np.asarray(x, dtype=np.float64)
        r = np.asarray(r, dtype=np.float64)
        if self._single:
            n = int(self._order[0])
            if x.shape != (n,):
                raise ValueError(
                    f"state has shape {x.shape}; plant '{self._systems[0]}' has {n} states"
                )
            x, r = x[None, :], r.reshape(1)
        else:
            B = len(self._systems)
            if x.ndim != 2 or x.shape[0] != B or x.shape[1] not in (MAX_ORDER, self._order.max()):
                raise ValueError(
                    f"state batch has shape {x.shape}; expected ({B}, {MAX_ORDER}) zero-padded"
                )
            if r.shape != (B,):
                raise ValueError(f"reference batch has shape {r.shape}; expected ({B},)")
        if not (np.isfinite(x).all() and np.isfinite(r).all()):
            raise ValueError("state or reference contains NaN or inf")
        self._padded[:, : x.shape[1]] = x
        return self._padded, r

    def window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The newest window ``(state, mask, ref, tag)`` the policy saw (after a step)."""
        b = self._buffer
        return b.state, b.mask, b.ref, self._tag

    def run_window(
        self, state: np.ndarray, mask: np.ndarray, ref: np.ndarray, tag: np.ndarray
    ) -> np.ndarray:
        """The backend's controls (B, horizon) for raw windows (no history bookkeeping)."""
        return self._run(state, mask, ref, tag)

    def step(self, x: Any, r: Any) -> float | np.ndarray:
        """Control for the current sample (the first of the predicted sequence)."""
        x, r = self._check(x, r)
        state, mask, ref = self._buffer.push(x, r)
        self.plan = self._run(state, mask, ref, self._tag)
        u = self.plan[:, 0].astype(np.float64)
        return float(u[0]) if self._single else u


class PolicyController:
    """Adapter: a :class:`PolicyRuntime` as the simulator's batch controller."""

    def __init__(self, runtime: PolicyRuntime) -> None:
        self.runtime = runtime

    def reset(self, plants: Sequence[Any], counts: Sequence[int]) -> None:
        """One batch row per run, plant names repeated by their counts."""
        self.runtime.reset([p.name for p, c in zip(plants, counts, strict=True) for _ in range(c)])

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls for zero-padded states."""
        return self.runtime.step(x, r)
