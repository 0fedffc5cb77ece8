"""MLflow for the evaluate stage, in a process started first: its imports overlap the work.

Importing MLflow and opening its store cost the evaluation a second or two, and it needs
neither until it logs its report folder to the evaluated model's run. :class:`MlflowWorker`
starts :mod:`~generalist_control.evaluation.mlflow_worker` at once; while the evaluation
loads the policy and simulates, that process imports MLflow and opens the store; at the end
it logs the folder (:func:`~generalist_control.evaluation.mlflow_log.log_to_mlflow`, as
before). :meth:`MlflowWorker.ready` waits for the store: the stage calls it before writing
anything, so a store that cannot be opened still stops the evaluation before its outputs
change, and before resolving a policy URI (``runs:/``, ``models:/``), which MLflow then
fetches in this process as before.

The stage's own command starts the worker earlier still (:func:`start_early`, before its
heavy imports and Hydra's composition): the worker imports MLflow meanwhile, then waits for
the config; the stage's :class:`MlflowWorker` takes that process over.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

__all__ = ["MlflowWorker", "MlflowWorkerError", "start_early"]

#: A worker started by :func:`start_early`, not yet taken by a :class:`MlflowWorker`.
_early: subprocess.Popen[str] | None = None


class MlflowWorkerError(RuntimeError):
    """MLflow failed in the worker: the message is its error, type first (masked)."""


def _spawn() -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "generalist_control.evaluation.mlflow_worker"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip


def start_early() -> None:
    """Start a worker now, for the next :class:`MlflowWorker` of this process to take.

    It imports MLflow while this process imports and composes its config, and does nothing
    else until it is sent the config; it ends when this process does (its stdin closes).
    """
    global _early
    if _early is None:
        _early = _spawn()


def _plain(value: Any) -> Any:
    """JSON for numpy scalars and arrays (NaN and inf stay, as JSON's extension has them)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


class MlflowWorker:
    """The MLflow worker process of one evaluation (a context manager that ends it).

    Parameters
    ----------
    logger : mapping
        The ``logger`` config (``tracking_uri``, ``experiment_name``, ...), plain values.
    prefix : str
        ``evaluation.mlflow_prefix``: the names' prefix in the model's run.
    """

    def __init__(self, logger: Mapping[str, Any], prefix: str) -> None:
        global _early
        early, _early = _early, None
        self._proc = early if early is not None and early.poll() is None else _spawn()
        self._uri: str | None = None
        self._send({"logger": dict(logger), "prefix": prefix})

    def _send(self, message: Mapping[str, Any]) -> None:
        assert self._proc.stdin is not None
        self._proc.stdin.write(json.dumps(message, default=_plain) + "\n")
        self._proc.stdin.flush()

    def _answer(self) -> dict[str, Any]:
        assert self._proc.stdout is not None
        line = self._proc.stdout.readline()
        if not line:
            raise MlflowWorkerError(
                f"the MLflow worker ended (exit code {self._proc.wait()}); its error is above"
            )
        reply = json.loads(line)
        if "error" in reply:
            raise MlflowWorkerError(reply["error"])
        return reply

    def ready(self) -> str:
        """Wait until MLflow is imported and the store open; the tracking URI.

        Raises
        ------
        MlflowWorkerError
            If the store cannot be opened (MLflow's error, type and message).
        """
        if self._uri is None:
            self._uri = str(self._answer()["uri"])
        return self._uri

    def log(self, run_id: str | None, summary: Mapping[str, Any], out_dir: Path) -> str | None:
        """Log ``summary``'s figures and ``out_dir`` to run ``run_id`` (or a new run); its id."""
        self.ready()
        self._send({"log": {"run_id": run_id, "summary": summary, "out_dir": str(out_dir)}})
        return self._answer()["run_id"]

    def close(self, at_once: bool = False) -> None:
        """End the worker: let it finish what it was sent, or (``at_once``) kill it."""
        if self._proc.poll() is None:
            try:
                if at_once:
                    raise OSError("killed")
                self._send({"quit": True})
                self._proc.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
        for stream in (self._proc.stdin, self._proc.stdout):
            if stream is not None and not stream.closed:
                stream.close()

    def __enter__(self) -> MlflowWorker:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close(at_once=exc is not None)
