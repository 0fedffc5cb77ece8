"""One Optuna trial: its values trained as one MLflow training run, the run's state kept in step.

The training itself is a function the entry point gives (``tune.py`` trains its config with
the trial's values set), so the study never holds the raw config.
"""

from __future__ import annotations

import logging
import math
import os
import socket
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import mlflow
import optuna
from mlflow.exceptions import MlflowException

from generalist_control.sweeps import stop_signals
from generalist_control.sweeps.search_space import Param
from generalist_control.sweeps.trial_callbacks import active_trial
from generalist_control.tracking.parents import parent_run

__all__ = ["Objective", "TrainPoint"]

log = logging.getLogger(__name__)

#: Train the config with ``values`` set, outputs in ``trial_dir``; return its metrics.
TrainPoint = Callable[[Mapping[str, Any], Path], Mapping[str, Any]]


class Objective:
    """Train one trial's values; return its metric.

    Parameters
    ----------
    train_point : callable
        ``(values, trial_dir) -> metrics``; run inside :func:`active_trial`, so the trial's
        callbacks (:mod:`~generalist_control.sweeps.trial_callbacks`) find the trial.
    space : list of Param
        What each trial draws.
    metric : str
        The key of the metrics returned (``hparams_search.metric``).
    trials_dir : Path
        Each trial trains in ``<trials_dir>/trial_<number>``.
    parent_id : str
        The study's MLflow parent run.
    """

    def __init__(
        self,
        train_point: TrainPoint,
        space: list[Param],
        metric: str,
        trials_dir: Path,
        parent_id: str,
    ) -> None:
        self.train_point = train_point
        self.space = space
        self.metric = metric
        self.trials_dir = trials_dir
        self.parent_id = parent_id

    def __call__(self, trial: optuna.Trial) -> float:
        """Train the trial's values; return its metric."""
        values = {p.key: p.suggest(trial) for p in self.space}
        trial_dir = self.trials_dir / f"trial_{trial.number:04d}"
        trial.set_user_attr("trial_dir", str(trial_dir))
        trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
        name = f"study:{trial.study.study_name}"
        try:
            with active_trial(trial), parent_run(self.parent_id, name):
                metrics = self.train_point(values, trial_dir)
        except optuna.TrialPruned:
            steps = trial.storage.get_trial(trial._trial_id).intermediate_values
            trial.set_user_attr("pruned_at_epoch", max(steps) if steps else None)
            self._end_run(trial, "PRUNED", "KILLED")
            raise
        except BaseException as exc:
            self._end_run(trial, "FAIL", None)  # the failed run already ended FAILED
            signum = stop_signals.received()
            if signum is not None and not isinstance(exc, stop_signals.Stopped):
                # Lightning turns the interrupt into SystemExit, which Optuna would not
                # catch (the trial would stay RUNNING): stop as the signal said
                raise stop_signals.Stopped(signum) from exc
            raise
        if self.metric not in metrics:
            raise KeyError(
                f"train() returned no metric {self.metric!r} (hparams_search.metric); "
                f"it has {sorted(metrics)}"
            )
        value = float(metrics[self.metric])
        numbers = {k: float(v) for k, v in metrics.items() if isinstance(v, int | float)}
        trial.set_user_attr("metrics", {k: v for k, v in numbers.items() if math.isfinite(v)})
        self._end_run(trial, "COMPLETE" if math.isfinite(value) else "FAIL", None)
        return value

    @staticmethod
    def _end_run(trial: optuna.Trial, state: str, status: str | None) -> None:
        """Tag the trial's MLflow run with the trial's state; set its status."""
        run_id = trial.user_attrs.get("mlflow_run_id")
        if not run_id:
            return
        try:
            client = mlflow.MlflowClient()
            client.set_tag(run_id, "optuna.state", state)
            if status:
                client.set_terminated(run_id, status)
        except MlflowException as e:  # never hide the trial's own outcome
            log.warning("could not update MLflow run %s of trial %d: %s", run_id, trial.number, e)
