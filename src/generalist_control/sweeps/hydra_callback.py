"""Grouped sweeps: one MLflow parent run per Hydra multirun, every job's run nested under it.

``python train.py -m model.hidden=16,32,64`` (or ``experts=1,3,5``, or both: the product)
runs one training per point. :class:`MLflowSweepCallback`, registered under
``hydra.callbacks`` in ``conf/config.yaml``, opens a *parent* run in the MLflow experiment of
kind ``sweep`` (``<logger.experiment_prefix>/sweep``, unless ``logger.experiment_name`` is
set; :mod:`generalist_control.tracking.experiments`) before the first job and exports its id
in ``GC_PARENT_RUN_ID`` (and the sweep's name in ``GC_SWEEP_NAME``); the training then files
every job's run in that experiment and tags it with ``mlflow.parentRunId`` and ``sweep``, so
the MLflow UI shows the points as children of one row and compares them side by side.
After the last job the parent gets a summary (``sweep/n_runs``, ``sweep/best/<metric>``,
tag ``sweep.best_run_id``) and ends ``FINISHED``, or ``FAILED`` if a job failed.

Hydra's basic launcher runs the jobs one after another in this process. A parallel launcher
runs them elsewhere: ``hydra/launcher=parallel`` or ``joblib`` in worker processes of this
machine (loky, which may reuse workers started for an earlier multirun, with that one's
environment), ``submitit_local`` and ``submitit_slurm`` in processes of their own, on a
cluster's nodes for SLURM. Each of them pickles Hydra's callbacks, this one with its
``run_id``, into the job, and :meth:`MLflowSweepCallback.on_job_start` sets the variables
there before the training starts: the parent reaches a job whatever its process inherited.

A single run (no ``-m``) with ``group`` set is filed under the parent run of that name in
its experiment, found or created by
:func:`generalist_control.tracking.parents.named_parent`: separate commands (the DVC
ablation's trainings, started two at a time) share one parent that way.
:func:`generalist_control.tracking.parents.parent_run` is the same mechanism for code (the
Optuna study of :mod:`generalist_control.sweeps.study` files its trials under a study run
with it).
"""

from __future__ import annotations

import atexit
import json
import logging
import os
from collections.abc import Sequence
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from generalist_control.common.configs import as_dict
from generalist_control.common.secrets import redact
from generalist_control.tracking import mlflow_utils
from generalist_control.tracking.experiments import experiment_name
from generalist_control.tracking.parents import (
    create_parent_run,
    named_parent,
    summarise_children,
)

__all__ = ["MLflowSweepCallback", "sweep_overrides"]

log = logging.getLogger(__name__)

_ENV_KEYS = (mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV)


def _set_env(values: Sequence[str]) -> dict[str, str | None]:
    """Set the parent's variables; return their previous values."""
    saved = {k: os.environ.get(k) for k in _ENV_KEYS}
    os.environ.update(dict(zip(_ENV_KEYS, values, strict=True)))
    return saved


def _restore_env(saved: dict[str, str | None]) -> None:
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


def sweep_overrides(overrides: Sequence[str]) -> list[str]:
    """The overrides of a Hydra command line that sweep (``a=1,2``, ``b=range(1,4)``, ...).

    Examples
    --------
    >>> sweep_overrides(["model.hidden=16,32", "trainer.max_epochs=5", "experts=1,3"])
    ['model.hidden=16,32', 'experts=1,3']
    """
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    return [str(o.input_line) for o in parsed if o.is_sweep_override()]


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
    group : str, optional
        A single run (no ``-m``) is filed under the parent run of this name in its
        experiment, made if missing (e.g. ``ablation:default``); a multirun ignores it.

    Each job of a multirun writes its model to ``<its output dir>/models`` unless
    ``paths.models_dir`` is on the command line
    (:attr:`generalist_control.training.settings.TrainingSettings.models_dir`),
    so the jobs overwrite neither each other's model nor the DVC output ``models/``.
    """

    def __init__(
        self, jobs: Sequence[str] = ("train",), name: str | None = None, group: str | None = None
    ) -> None:
        self.jobs = tuple(jobs)
        self.name = name
        self.group = group
        self.run_id: str | None = None
        self._parent_name: str | None = None
        self._failed = 0
        self._tracking_uri: str | None = None
        self._saved_env: dict[str, str | None] = {}
        self._job_env: dict[str, str | None] | None = None

    def _active(self, config: DictConfig) -> bool:
        return str(config.hydra.job.name) in self.jobs

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Create the parent run and export its id to the jobs."""
        if not self._active(config):
            return
        import mlflow  # only a sweep that logs pays for its import
        from mlflow.entities import RunStatus

        overrides = [str(o) for o in config.hydra.overrides.task]
        swept = [redact(o) for o in sweep_overrides(overrides)]
        overrides = [redact(o) for o in overrides]  # no password reaches the parent run
        name = self.name or "sweep:" + " ".join(swept or overrides or ["(no overrides)"])
        tags = {
            "sweep.overrides": json.dumps(overrides)[:5000],
            "sweep.swept": json.dumps(swept)[:5000],
            "sweep.dir": str(config.hydra.sweep.dir),
        }
        logger = as_dict(config.logger)
        logger["experiment_name"] = experiment_name(logger, "sweep")  # the jobs follow it
        self.run_id = create_parent_run(logger, name, "sweep", tags)
        self._parent_name = name
        self._tracking_uri = mlflow.get_tracking_uri()
        self._failed = 0
        self._saved_env = _set_env((self.run_id, name))
        # A failed job makes Hydra raise before on_multirun_end: end the parent at exit then.
        atexit.register(self._end, RunStatus.to_string(RunStatus.FAILED))
        log.info("MLflow sweep %r: parent run %s", name, self.run_id)

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        """A single run with ``group`` set: find or make that parent, export it to the job."""
        if not self.group or not self._active(config):
            return
        logger = as_dict(config.logger)
        self.run_id = named_parent(logger, self.group, kind="train")
        self._parent_name = self.group
        log.info("MLflow group %r: parent run %s", self.group, self.run_id)

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Export the parent to this job, in whichever process the launcher runs it."""
        if self.run_id and self._parent_name and self._active(config):
            self._job_env = _set_env((self.run_id, self._parent_name))

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        """Count the failed jobs (the parent then ends ``FAILED``); restore the environment."""
        if self._job_env is not None:
            _restore_env(self._job_env)
            self._job_env = None
        if self.run_id and job_return.status == JobStatus.FAILED:
            self._failed += 1

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Forget a group's parent (it stays ``FINISHED``: it has no work of its own)."""
        if self.group and self._active(config):
            self.run_id = self._parent_name = None

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Summarise the children into the parent and end it."""
        if self.run_id is None:
            return
        import mlflow
        from mlflow.entities import RunStatus

        try:
            if self._tracking_uri:
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
        import mlflow

        run_id, self.run_id = self.run_id, None
        atexit.unregister(self._end)
        _restore_env(self._saved_env)
        self._parent_name = None
        if self._tracking_uri:
            mlflow.set_tracking_uri(self._tracking_uri)
        mlflow.MlflowClient().set_terminated(run_id, status)
