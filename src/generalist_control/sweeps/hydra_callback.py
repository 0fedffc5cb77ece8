"""One MLflow parent run per Hydra multirun of the training, every job's run nested under it.

The callback also runs, pickled, in each job's process (joblib, submitit), where it exports
the parent before the training starts. SIGTERM or SIGINT stops the sweep (docs/sweeps.md).
"""

from __future__ import annotations

import atexit
import json
import logging
from collections.abc import Sequence
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from generalist_control.common import stop_signals
from generalist_control.common.secrets import redact
from generalist_control.common.sections import as_dict
from generalist_control.tracking import mlflow_utils
from generalist_control.tracking.mlflow_utils import experiment_name
from generalist_control.tracking.parents import (
    create_parent_run,
    named_parent,
    parent_env,
    summarise_children,
)

__all__ = ["MLflowSweepCallback", "sweep_overrides"]

log = logging.getLogger(__name__)


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
        Hydra job names (``hydra.job.name``) whose multiruns are grouped.
    name : str or None
        The parent run's name and the children's ``sweep`` tag; None: ``sweep:`` followed by
        the sweeping overrides, e.g. ``sweep:model.hidden=16,32,64``.
    group : str or None
        A single run (no ``-m``) is filed under the parent run of this name, made if missing
        (:func:`~generalist_control.tracking.parents.named_parent`); a multirun ignores it.
    """

    def __init__(self, *, jobs: Sequence[str], name: str | None, group: str | None) -> None:
        self.jobs = tuple(jobs)
        self.name = name
        self.group = group
        self.run_id: str | None = None
        self._parent_name: str | None = None
        self._failed = 0
        self._tracking_uri = ""  #: the parent's store (set with it)
        self._saved_env: dict[str, str | None] = {}
        self._job_env: dict[str, str | None] | None = None
        self._stops = False

    def _active(self, config: DictConfig) -> bool:
        return str(config.hydra.job.name) in self.jobs

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Create the parent run and export its id to the jobs."""
        if not self._active(config):
            return
        import mlflow  # only a sweep that logs pays for its import

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
        self._saved_env = mlflow_utils.swap_env(parent_env(self.run_id, name))
        # A failed job or a signal makes Hydra raise before on_multirun_end: end it at exit.
        atexit.register(self._end_at_exit)
        self._stops = stop_signals.install()
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
            self._job_env = mlflow_utils.swap_env(parent_env(self.run_id, self._parent_name))

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        """Count the failed jobs (the parent then ends ``FAILED``); restore the environment."""
        if self._job_env is not None:
            mlflow_utils.swap_env(self._job_env)
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

        try:
            mlflow.set_tracking_uri(self._tracking_uri)
            summary = summarise_children(self.run_id, str(config.optimized_metric))
            log.info("MLflow sweep %s: %s", self.run_id, summary)
        finally:
            self._end("FAILED" if self._failed else "FINISHED")

    def _end_at_exit(self) -> None:
        """The process exits before ``on_multirun_end``: a job failed, or a signal stopped it."""
        self._end("FAILED" if stop_signals.received() is None else "KILLED")

    def _end(self, status: str) -> None:
        if self.run_id is None:
            return
        import mlflow

        run_id, self.run_id = self.run_id, None
        atexit.unregister(self._end_at_exit)
        if self._stops:
            stop_signals.restore()
        mlflow_utils.swap_env(self._saved_env)
        self._parent_name = None
        mlflow.set_tracking_uri(self._tracking_uri)
        client = mlflow.MlflowClient()
        if status == "KILLED":  # the jobs' runs whose process the launcher killed
            mlflow_utils.end_stale_runs(client.get_run(run_id).info.experiment_id)
        client.set_terminated(run_id, status)
