"""The MLflow side of the evaluate stage, as a process of its own (``python -m`` this module).

Started by :class:`~generalist_control.evaluation.tracker.MlflowWorker` before the evaluation
imports anything heavy, it imports MLflow and opens the tracking store
(:func:`~generalist_control.tracking.mlflow_utils.set_tracking`) while the evaluation runs,
then logs what it is sent (:func:`~generalist_control.evaluation.mlflow_log.log_to_mlflow`).

MLflow and its SQL store's module (the default store's) are imported before the first line
is read (a worker started early, :func:`~generalist_control.evaluation.tracker.start_early`,
imports them while the evaluation composes its config); a stdin that closes before that line
ends it without opening a store.

Protocol: JSON lines. In on stdin: first ``{"logger": ..., "prefix": ...}``, then
``{"log": {"run_id", "summary", "out_dir"}}`` per evaluation; anything else ends it. Out on
stdout, one line per request: ``{"uri": ...}`` once the store is open, ``{"run_id": ...}``
per log, or ``{"error": "<type>: <message>"}`` (credentials masked). Whatever else prints
goes to stderr.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any, TextIO

from omegaconf import OmegaConf

from generalist_control.common.secrets import redact
from generalist_control.evaluation.mlflow_log import log_to_mlflow
from generalist_control.tracking.mlflow_utils import set_tracking

__all__ = ["main"]


def _answer(out: TextIO, work: Callable[[], dict[str, Any]]) -> bool:
    """Write ``work()``'s reply (or its error) as one line; whether it succeeded."""
    try:
        reply = work()
    except Exception as exc:  # noqa: BLE001 - every error goes back to the evaluation
        reply = {"error": redact(f"{type(exc).__module__}.{type(exc).__qualname__}: {exc}")}
    out.write(json.dumps(reply) + "\n")
    out.flush()
    return "error" not in reply


def _log(cfg: Any, req: dict[str, Any]) -> dict[str, Any]:
    meta = {"mlflow_run_id": req["run_id"]}
    return {"run_id": log_to_mlflow(cfg, meta, req["summary"], Path(req["out_dir"]))}


def _import_sql_store() -> None:
    """Import the SQL store's module and set up its ORM mappers (about a second).

    The default store is SQLite, and opening one would do both; done here, before the
    config comes, it runs while the evaluation composes its config, not beside its
    simulation. The store itself is opened only once the config names it.
    """
    from mlflow.store.tracking import sqlalchemy_store  # noqa: F401
    from sqlalchemy.orm import configure_mappers

    configure_mappers()


def main() -> None:
    """Serve one evaluation: open the store, then log what comes (module docstring)."""
    replies, sys.stdout = sys.stdout, sys.stderr  # MLflow's own prints stay off the pipe
    import mlflow  # noqa: F401 - imported while the evaluation gets ready

    _import_sql_store()

    first = sys.stdin.readline()
    if not first:  # the evaluation ended (or never needed us): nothing to open
        return
    start = json.loads(first)
    cfg = OmegaConf.create(
        {"logger": start.get("logger", {}), "evaluation": {"mlflow_prefix": start.get("prefix")}}
    )
    if not _answer(replies, lambda: {"uri": set_tracking(cfg.logger)}):
        return
    for line in sys.stdin:
        req = json.loads(line).get("log")
        if req is None:
            break
        _answer(replies, partial(_log, cfg, req))
    # Every log was answered, so it is in the store (MLflow logs synchronously here): skip
    # the interpreter's shutdown with MLflow loaded, about a second the evaluation waits for.
    sys.stderr.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
