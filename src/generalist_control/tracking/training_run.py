"""The MLflow run of a training: Lightning's ``MLFlowLogger``, plus what it cannot do.

The experiment is made beforehand under the store's lock, stale runs are ended, the run is
nested under its sweep; :class:`RunRecorder` logs per epoch and keeps the run id for a resume.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

import lightning as L
import mlflow
import torch
from lightning.pytorch.loggers import MLFlowLogger
from mlflow.exceptions import MlflowException

from generalist_control.common.secrets import redact
from generalist_control.common.sections import ConfigTree, lookup
from generalist_control.tracking import mlflow_utils

__all__ = [
    "logger_run",
    "RunRecorder",
    "log_params_once",
    "run_id_from_checkpoint",
    "training_logger",
    "training_params",
]

log = logging.getLogger(__name__)

#: Metric prefixes the recorder sends to MLflow after every epoch.
EPOCH_METRICS = ("train/", "val/", "dagger/")


def training_params(tree: ConfigTree, keys: Sequence[str]) -> dict[str, str]:
    """The params of a training run: the ``keys`` of the resolved config ``tree``, flattened.

    A part (a node with ``_target_``) is logged as its class name, then its non-null settings.

    Examples
    --------
    >>> tree = {"model": {"_target_": "pkg.Net", "hidden": 64, "skip": None}, "dagger": None}
    >>> training_params(tree, ["model", "dagger", "nowhere"])
    {'model': 'Net', 'model.hidden': '64', 'dagger': 'None'}
    """
    out: dict[str, str] = {}
    for key in keys:
        found, node = lookup(tree, key)
        if found and node is None:
            out[key] = "None"
        elif found:
            for name, value in mlflow_utils.flatten_params({key: node}, ()).items():
                if name.endswith("._target_"):
                    out[name[: -len("._target_")]] = value.rsplit(".", 1)[-1]
                elif not name.endswith("._partial_") and value != "None":
                    out[name] = value
    return out


def _stored_run(run_id: str | None, missing: str) -> Any:
    """The run ``run_id`` if the current store holds it, else None (``missing`` is logged)."""
    if not run_id:
        return None
    try:
        return mlflow.MlflowClient().get_run(run_id)
    except MlflowException:
        log.warning(missing, run_id)
        return None


def training_logger(logger: Mapping[str, Any], resume_run_id: str | None = None) -> MLFlowLogger:
    """Lightning's MLflow logger on the training's run, which exists when this returns.

    ``resume_run_id``: the run to continue (:func:`run_id_from_checkpoint`), if this store
    holds it. A new run goes to its parent's experiment, else to that of kind ``train``.
    """
    mlflow_utils.set_tracking(logger)
    parent_id = os.environ.get(mlflow_utils.PARENT_RUN_ENV)
    parent = _stored_run(parent_id, "parent run %s is not in this MLflow store; not nesting")
    exp_id = parent.info.experiment_id if parent else mlflow_utils.experiment_id(logger)
    client = mlflow.MlflowClient()
    mlflow_utils.end_stale_runs(exp_id)
    resumed = _stored_run(resume_run_id, "MLflow run %s of the checkpoint is not in this store")
    run_id = resumed.info.run_id if resumed else None
    tags = None if run_id else {**mlflow_utils.parent_run_tags(), **mlflow_utils.process_tags()}
    run_name = redact(logger.get("run_name"))
    mlf = MLFlowLogger(
        experiment_name=client.get_experiment(exp_id).name,
        run_name=None if run_id or not run_name else str(run_name),
        tracking_uri=mlflow.get_tracking_uri(),
        tags=tags,
        log_model=False,  # the project logs its own policy
        run_id=run_id,
    )
    if mlf.run_id is None:  # creates the run now
        raise RuntimeError("MLFlowLogger made no run")
    if run_id:
        client.set_tag(run_id, "resumed", "true")
        for key, value in mlflow_utils.process_tags().items():
            client.set_tag(run_id, key, value)
    return mlf


class RunRecorder(L.Callback):
    """Send each epoch's metrics, ``lr`` and ``time/epoch_s`` to the logger at step = epoch.

    Also renews the run's heartbeat tag and keeps ``run_id`` in the checkpoint.
    """

    def __init__(self, run_id: str) -> None:
        self.run_id = run_id
        self._t0 = time.perf_counter()
        self._lr = float("nan")

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Start the epoch's clock and note the learning rate it trains with."""
        self._t0 = time.perf_counter()
        self._lr = float(trainer.optimizers[0].param_groups[0]["lr"])

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """After the epoch's validation: its metrics, at step ``current_epoch``."""
        metrics = {
            k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith(EPOCH_METRICS)
        }
        metrics["lr"] = self._lr
        metrics["time/epoch_s"] = time.perf_counter() - self._t0
        mlf = cast(MLFlowLogger, trainer.logger)  # the training's (:func:`training_logger`)
        mlf.log_metrics(metrics, step=trainer.current_epoch)
        mlf.experiment.set_tag(self.run_id, mlflow_utils.HEARTBEAT_TAG, mlflow_utils.now())

    def state_dict(self) -> dict[str, Any]:
        """Checkpoint state: the run id."""
        return {"run_id": self.run_id}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Keep the current run id (the resumed run is chosen before fitting)."""


#: Names under which a checkpoint keeps the run id (``MLflowEpochLogger``: older checkpoints).
_STATE_KEYS = (RunRecorder.__qualname__, "MLflowEpochLogger")


def run_id_from_checkpoint(ckpt_path: str | Path) -> str | None:
    """The MLflow run id that :class:`RunRecorder` kept in a Lightning checkpoint."""
    blob = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    states = blob.get("callbacks", {})
    for key in _STATE_KEYS:
        if states.get(key, {}).get("run_id"):
            return str(states[key]["run_id"])
    return None


def log_params_once(params: Mapping[str, str]) -> dict[str, tuple[str, str]]:
    """Log params to the active run but those it has (a resume); return ``{key: (old, new)}``.

    The changed ones are also written to the tag ``resume.changed_params``.
    """
    run = mlflow.active_run()
    old = mlflow.get_run(run.info.run_id).data.params if run else {}
    changed = {k: (old[k], v) for k, v in params.items() if k in old and old[k] != v}
    mlflow.log_params({k: v for k, v in params.items() if k not in old})
    if changed:
        mlflow.set_tag("resume.changed_params", json.dumps(changed)[: mlflow_utils.MAX_VALUE])
    return changed


@contextmanager
def logger_run(logger: MLFlowLogger) -> Iterator[Any]:
    """The fluent API on the Lightning logger's run within the block.

    ``start_run(run_id=...)`` refuses a run of another experiment than the active one: the
    run's own is made active for the block, then the active one is put back.
    """
    from mlflow.tracking import fluent

    saved = fluent._active_experiment_id
    env = {"MLFLOW_EXPERIMENT_ID": os.environ.get("MLFLOW_EXPERIMENT_ID")}
    mlflow.set_experiment(experiment_id=logger.experiment_id)
    try:
        with mlflow.start_run(run_id=logger.run_id) as run:
            yield run
    finally:
        fluent._active_experiment_id = saved
        mlflow_utils.swap_env(env)
