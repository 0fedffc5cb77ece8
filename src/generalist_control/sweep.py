"""Grouped sweeps: one MLflow parent run per Hydra multirun, every job's run nested under it.

``python train.py -m model.hidden=16,32,64`` (or ``experts=1,3,5``, or both: the product)
runs one training per point. :class:`MLflowSweepCallback`, registered under
``hydra.callbacks`` in ``conf/config.yaml``, opens a *parent* run in the training's MLflow
experiment before the first job and exports its id in ``GC_PARENT_RUN_ID`` (and the sweep's
name in ``GC_SWEEP_NAME``); :func:`generalist_control.mlflow_utils.mlflow_run` then tags
every job's run with ``mlflow.parentRunId`` and ``sweep``, so the MLflow UI shows the points
as children of one row and compares them side by side. After the last job the parent gets a
summary (``sweep/n_runs``, ``sweep/best/<metric>``, tag ``sweep.best_run_id``) and ends
``FINISHED``, or ``FAILED`` if a job failed.

Hydra's basic launcher runs the jobs one after another in this process; a launcher that
starts worker processes inherits the environment, so the jobs still find their parent.
:func:`parent_run` is the same mechanism for code (the Optuna study of
:mod:`generalist_control.tune` files its trials under a study run with it).
"""

from __future__ import annotations

import atexit
import json
import logging
import math
import os
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import mlflow
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from mlflow.entities import RunStatus
from omegaconf import DictConfig

from generalist_control import mlflow_utils

__all__ = [
    "MLflowSweepCallback",
    "create_parent_run",
    "parent_run",
    "summarise_children",
    "sweep_overrides",
]

log = logging.getLogger(__name__)

#: Tag that marks a parent run and says what it groups (``sweep`` or ``study``).
ROLE_TAG = "gc.role"


def sweep_overrides(overrides: Sequence[str]) -> list[str]:
    """The overrides of a Hydra command line that sweep (``a=1,2``, ``b=range(1,4)``, ...).

    Examples
    --------
    >>> sweep_overrides(["model.hidden=16,32", "trainer.max_epochs=5", "experts=1,3"])
    ['model.hidden=16,32', 'experts=1,3']
    """
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    return [o.input_line for o in parsed if o.is_sweep_override()]


def create_parent_run(
    logger: Mapping[str, Any],
    name: str,
    role: str,
    tags: Mapping[str, str] | None = None,
) -> str:
    """Create a ``RUNNING`` parent run in ``logger``'s experiment; return its id.

    Parameters
    ----------
    logger : mapping
        The ``logger`` config (tracking URI, experiment name, artifact location).
    name : str
        Run name, shown in the MLflow UI; also the children's ``sweep`` tag.
    role : str
        What the parent groups: ``"sweep"`` (a multirun) or ``"study"`` (Optuna).
    tags : mapping, optional
        Further tags of the parent run.
    """
    exp_id = mlflow_utils.experiment_id(logger)
    run = mlflow.MlflowClient().create_run(
        exp_id, run_name=name, tags={ROLE_TAG: role, "sweep": name, **(tags or {})}
    )
    return run.info.run_id


@contextmanager
def parent_run(run_id: str, name: str) -> Iterator[None]:
    """Within the block, new training runs are children of ``run_id`` (tag ``sweep=name``).

    The previous values of ``GC_PARENT_RUN_ID`` and ``GC_SWEEP_NAME`` come back afterwards.
    """
    keys = (mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV)
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update(dict(zip(keys, (run_id, name), strict=True)))
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def summarise_children(parent_id: str, metric: str = "val/loss", mode: str = "min") -> dict:
    """Log a summary of the parent's child runs to the parent; return it.

    Parameters
    ----------
    parent_id : str
        The parent run (its experiment is searched for runs tagged with it).
    metric : str
        The children's score: their ``best/<metric>`` if logged, else ``<metric>``.
    mode : {"min", "max"}
        Whether lower or higher is better.

    Returns
    -------
    dict
        ``n_runs``, ``n_finished`` and, when a child has the metric, ``best_value`` and
        ``best_run_id``; logged as ``sweep/n_runs``, ``sweep/n_finished``,
        ``sweep/best/<metric>`` and the tag ``sweep.best_run_id``.
    """
    if mode not in ("min", "max"):
        raise ValueError(f"mode must be 'min' or 'max', not {mode!r}")
    client = mlflow.MlflowClient()
    parent = client.get_run(parent_id)
    children = client.search_runs(
        [parent.info.experiment_id],
        filter_string=f"tags.mlflow.parentRunId = '{parent_id}'",
        max_results=10_000,
    )
    summary: dict[str, Any] = {
        "n_runs": len(children),
        "n_finished": sum(c.info.status == "FINISHED" for c in children),
    }
    scored = []
    for child in children:
        value = child.data.metrics.get(f"best/{metric}", child.data.metrics.get(metric))
        if value is not None and math.isfinite(value):
            scored.append((value, child.info.run_id))
    metrics = {"sweep/n_runs": summary["n_runs"], "sweep/n_finished": summary["n_finished"]}
    if scored:
        best_value, best_id = (min if mode == "min" else max)(scored)
        summary.update(best_value=best_value, best_run_id=best_id)
        metrics[f"sweep/best/{metric}"] = best_value
        client.set_tag(parent_id, "sweep.best_run_id", best_id)
    for key, value in metrics.items():
        client.log_metric(parent_id, key, float(value))
    return summary


class MLflowSweepCallback(Callback):
    """Hydra callback: one MLflow parent run per multirun of the training.

    Parameters
    ----------
    jobs : sequence of str
        Hydra job names (``hydra.job.name``) whose multiruns are grouped; other entry points
        sharing ``conf/config.yaml`` (``generate``, ``evaluate``) log no MLflow runs and get
        no parent.
    name : str, optional
        The parent run's name and the children's ``sweep`` tag; default ``sweep:`` followed
        by the sweeping overrides, e.g. ``sweep:model.hidden=16,32,64``.

    Each job of a multirun writes its model to ``<its output dir>/models`` unless
    ``paths.models_dir`` is on the command line (:func:`generalist_control.train.models_dir`),
    so the jobs overwrite neither each other's model nor the DVC output ``models/``.
    """

    def __init__(self, jobs: Sequence[str] = ("train",), name: str | None = None) -> None:
        self.jobs = tuple(jobs)
        self.name = name
        self.run_id: str | None = None
        self._failed = 0
        self._tracking_uri: str | None = None
        self._saved_env: dict[str, str | None] = {}

    def _active(self, config: DictConfig) -> bool:
        return str(config.hydra.job.name) in self.jobs

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Create the parent run and export its id to the jobs."""
        if not self._active(config):
            return
        overrides = [str(o) for o in config.hydra.overrides.task]
        swept = sweep_overrides(overrides)
        name = self.name or "sweep:" + " ".join(swept or overrides or ["(no overrides)"])
        tags = {
            "sweep.overrides": json.dumps(overrides)[:5000],
            "sweep.swept": json.dumps(swept)[:5000],
            "sweep.dir": str(config.hydra.sweep.dir),
        }
        self.run_id = create_parent_run(config.logger, name, "sweep", tags)
        self._tracking_uri = mlflow.get_tracking_uri()
        self._failed = 0
        keys = (mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV)
        self._saved_env = {k: os.environ.get(k) for k in keys}
        os.environ.update(dict(zip(keys, (self.run_id, name), strict=True)))
        # A failed job makes Hydra raise before on_multirun_end: end the parent at exit then.
        atexit.register(self._end, RunStatus.to_string(RunStatus.FAILED))
        log.info("MLflow sweep %r: parent run %s", name, self.run_id)

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        """Count the failed jobs (the parent then ends ``FAILED``)."""
        if self.run_id and job_return.status == JobStatus.FAILED:
            self._failed += 1

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Summarise the children into the parent and end it."""
        if self.run_id is None:
            return
        try:
            mlflow.set_tracking_uri(self._tracking_uri)
            metric = str(config.get("optimized_metric") or "val/loss")
            summary = summarise_children(self.run_id, metric)
            log.info("MLflow sweep %s: %s", self.run_id, summary)
        finally:
            status = RunStatus.FAILED if self._failed else RunStatus.FINISHED
            self._end(RunStatus.to_string(status))

    def _end(self, status: str) -> None:
        if self.run_id is None:
            return
        run_id, self.run_id = self.run_id, None
        atexit.unregister(self._end)
        for key, value in self._saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        if self._tracking_uri:
            mlflow.set_tracking_uri(self._tracking_uri)
        mlflow.MlflowClient().set_terminated(run_id, status)
