"""MLflow, one mechanism: the fluent API on one run opened by :func:`mlflow_run`.

By default runs go to an embedded store in the working directory, an SQLite database
(``sqlite:///mlflow.db``) plus an artifact folder (``mlruns/``), which ``mlflow ui`` run in
the repository shows. ``logger.tracking_uri`` (or ``MLFLOW_TRACKING_URI``) points it at a
server instead; the server then decides where artifacts go.

Each training run records the resolved config flattened into params, the data's content
hash as the tag ``data.content_hash`` (and DVC's hash of the data directory, when
``dvc.lock`` has it), per-epoch metrics through :class:`MLflowEpochLogger`, and artifacts
logged by :mod:`generalist_control.train`.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import lightning as L
import mlflow
import torch
import yaml
from mlflow.exceptions import MlflowException

__all__ = [
    "PARENT_RUN_ENV",
    "SWEEP_ENV",
    "MLflowEpochLogger",
    "dvc_data_version",
    "experiment_id",
    "flatten_params",
    "log_params_once",
    "mlflow_run",
    "parent_run_tags",
    "run_id_from_checkpoint",
    "tracking_uri",
]

#: Config subtrees left out of the params: the plant models (fixed by the data hash, and in
#: the logged manifest) and Hydra's own settings.
EXCLUDED = ("systems.plants", "hydra")
_MAX_VALUE = 6000  # MLflow's limit on a param value

#: Environment variables through which a sweep (:mod:`generalist_control.sweep`) or a study
#: (:mod:`generalist_control.tune`) hands its parent run to the training runs it starts.
PARENT_RUN_ENV = "GC_PARENT_RUN_ID"
SWEEP_ENV = "GC_SWEEP_NAME"


def tracking_uri(logger: Mapping[str, Any]) -> str:
    """The tracking URI from ``logger.tracking_uri`` (default: the embedded SQLite store)."""
    return str(logger.get("tracking_uri") or "sqlite:///mlflow.db")


def set_tracking(logger: Mapping[str, Any]) -> str:
    """Point MLflow at the ``logger`` config's tracking URI; return it."""
    uri = tracking_uri(logger)
    mlflow.set_tracking_uri(uri)
    return uri


def _is_local(uri: str) -> bool:
    return uri.startswith(("sqlite:", "file:")) or "://" not in uri


def flatten_params(cfg: Mapping[str, Any], exclude: tuple[str, ...] = EXCLUDED) -> dict[str, str]:
    """Flatten a (resolved) config into ``{"a.b.c": "value"}``; lists become JSON.

    Examples
    --------
    >>> flatten_params({"model": {"hidden": 64}, "experts": 5, "hydra": {"x": 1}})
    {'model.hidden': '64', 'experts': '5'}
    """
    out: dict[str, str] = {}

    def walk(node: Any, prefix: str) -> None:
        if prefix in exclude:
            return
        if isinstance(node, Mapping):
            for key, value in node.items():
                walk(value, f"{prefix}.{key}" if prefix else str(key))
        else:
            text = json.dumps(node) if isinstance(node, list | tuple) else str(node)
            out[prefix] = text[:_MAX_VALUE]

    walk(cfg, "")
    return out


def dvc_data_version(data_dir: str | Path, lock: str | Path = "dvc.lock") -> str | None:
    """DVC's hash of ``data_dir`` as recorded in ``dvc.lock`` (an ``outs`` entry), if any."""
    lock = Path(lock)
    if not lock.is_file():
        return None
    target = Path(data_dir).as_posix().rstrip("/")
    stages = (yaml.safe_load(lock.read_text()) or {}).get("stages", {})
    for stage in stages.values():
        for out in stage.get("outs", []):
            if str(out.get("path", "")).rstrip("/") == target:
                return out.get("md5") or out.get("hash")
    return None


def run_id_from_checkpoint(ckpt_path: str | Path) -> str | None:
    """The MLflow run id saved by :class:`MLflowEpochLogger` in a Lightning checkpoint."""
    blob = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    state = blob.get("callbacks", {}).get(MLflowEpochLogger.__qualname__, {})
    return state.get("run_id")


@contextmanager
def mlflow_run(
    logger: Mapping[str, Any], resume_run_id: str | None = None
) -> Iterator[mlflow.ActiveRun]:
    """Open the training's run: the one ``resume_run_id`` names, if it exists, else a new one.

    Parameters
    ----------
    logger : mapping
        The ``logger`` config: ``tracking_uri``, ``experiment_name``, ``artifact_location``
        (used when creating the experiment in a local store), ``run_name``.
    resume_run_id : str, optional
        Run to continue (a resumed training keeps logging into its run).

    Notes
    -----
    Inside a sweep or an Optuna study, a new run is nested under the parent run given by
    the environment (:func:`parent_run_tags`).
    """
    exp_id = experiment_id(logger)
    run_id = None
    if resume_run_id:
        try:
            run_id = mlflow.get_run(resume_run_id).info.run_id
        except MlflowException:
            run_id = None  # the checkpoint comes from another store: start a new run
    with mlflow.start_run(
        run_id=run_id,
        experiment_id=None if run_id else exp_id,
        run_name=None if run_id else logger.get("run_name"),
        tags=None if run_id else parent_run_tags() or None,
    ) as run:
        yield run


def experiment_id(logger: Mapping[str, Any]) -> str:
    """Point MLflow at ``logger``'s store; the id of its experiment, created if missing."""
    uri = set_tracking(logger)
    name = str(logger.get("experiment_name") or "generalist-control")
    experiment = mlflow.get_experiment_by_name(name)
    if experiment is not None:
        return experiment.experiment_id
    location = logger.get("artifact_location")
    if location and _is_local(uri) and "://" not in str(location):
        location = Path(location).resolve().as_uri()
    try:
        return mlflow.create_experiment(name, artifact_location=location or None)
    except MlflowException:
        experiment = mlflow.get_experiment_by_name(name)  # another worker created it first
        if experiment is None:
            raise
        return experiment.experiment_id


def parent_run_tags() -> dict[str, str]:
    """Tags that file a new run under the parent run named by ``GC_PARENT_RUN_ID``, if set.

    ``mlflow.parentRunId`` nests the run under its sweep (or study) in the MLflow UI;
    ``sweep`` carries the sweep's name (``GC_SWEEP_NAME``).
    """
    parent = os.environ.get(PARENT_RUN_ENV)
    if not parent:
        return {}
    tags = {"mlflow.parentRunId": parent}
    if os.environ.get(SWEEP_ENV):
        tags["sweep"] = os.environ[SWEEP_ENV]
    return tags


def log_params_once(params: Mapping[str, str]) -> dict[str, tuple[str, str]]:
    """Log params to the active run, skipping those it already has (a resumed run).

    Returns the params whose value differs from the one already logged, ``{key: (old,
    new)}``; they are also written to the tag ``resume.changed_params``.
    """
    run = mlflow.active_run()
    old = mlflow.get_run(run.info.run_id).data.params if run else {}
    changed = {k: (old[k], v) for k, v in params.items() if k in old and old[k] != v}
    mlflow.log_params({k: v for k, v in params.items() if k not in old})
    if changed:
        mlflow.set_tag("resume.changed_params", json.dumps(changed)[:_MAX_VALUE])
    return changed


class MLflowEpochLogger(L.Callback):
    """Log the epoch's ``train/*`` and ``val/*`` metrics and the learning rate to MLflow.

    The run id is part of the callback's checkpoint state, so a resumed training finds its
    run again (:func:`run_id_from_checkpoint`).
    """

    def __init__(self, run_id: str | None = None) -> None:
        self.run_id = run_id
        self._t0 = time.perf_counter()
        self._lr = float("nan")

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Start the epoch's clock and note the learning rate it trains with."""
        self._t0 = time.perf_counter()
        self._lr = float(trainer.optimizers[0].param_groups[0]["lr"])

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Log after the epoch's validation, with the epoch number as the step."""
        if trainer.sanity_checking or self.run_id is None:
            return
        metrics = {
            k: float(v)
            for k, v in trainer.callback_metrics.items()
            if k.startswith(("train/", "val/"))
        }
        metrics["lr"] = self._lr
        metrics["time/epoch_s"] = time.perf_counter() - self._t0
        mlflow.log_metrics(metrics, step=trainer.current_epoch, run_id=self.run_id)

    def state_dict(self) -> dict[str, Any]:
        """Checkpoint state: the run id."""
        return {"run_id": self.run_id}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Keep the current run id (the resumed run is opened before fitting)."""
