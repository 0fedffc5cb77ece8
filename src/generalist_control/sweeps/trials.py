"""One Optuna trial: its training config, the training run, and its MLflow run's state."""

from __future__ import annotations

import copy
import logging
import math
import os
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mlflow
import optuna
from mlflow.exceptions import MlflowException
from omegaconf import DictConfig, OmegaConf, open_dict

from generalist_control.sweeps.pruning import active_trial, trial_pruning, trial_run_link
from generalist_control.sweeps.space import Param
from generalist_control.tracking.parents import parent_run
from generalist_control.training.fit import train
from generalist_control.training.settings import read_training

__all__ = ["Objective", "trial_config"]

log = logging.getLogger(__name__)


def trial_config(
    cfg: DictConfig,
    values: Mapping[str, Any],
    trial_dir: Path,
    monitor: str = "val/loss",
    experiment: str | None = None,
) -> DictConfig:
    """The training config of one trial: ``cfg`` with ``values`` set, outputs in ``trial_dir``.

    The search's own section (``hparams_search``) is dropped, the checkpoints go to
    ``<trial_dir>/run`` and the model to ``<trial_dir>/models``, ``experiment`` (the study's,
    of kind ``tune``) becomes ``logger.experiment_name`` if given, and the callbacks get the
    pruning (:func:`~generalist_control.sweeps.pruning.trial_pruning`) and the trial-run link
    (:func:`~generalist_control.sweeps.pruning.trial_run_link`).
    """
    tcfg = copy.deepcopy(cfg)
    with open_dict(tcfg):
        tcfg.pop("hparams_search", None)
        for key, value in values.items():
            OmegaConf.update(tcfg, key, value, merge=False)
        tcfg.run_dir = str(trial_dir / "run")
        tcfg.paths.models_dir = str(trial_dir / "models")
        if experiment is not None:
            tcfg.logger.experiment_name = experiment
        if tcfg.get("callbacks") is None:
            tcfg.callbacks = {}
        tcfg.callbacks.optuna_pruning = {
            "_target_": f"{trial_pruning.__module__}.{trial_pruning.__name__}",
            "monitor": monitor,
        }
        tcfg.callbacks.optuna_run_link = {
            "_target_": f"{trial_run_link.__module__}.{trial_run_link.__name__}",
        }
    return tcfg


class Objective:
    """Train one trial's config; return its metric."""

    def __init__(
        self,
        cfg: DictConfig,
        space: list[Param],
        search: DictConfig,
        trials_dir: Path,
        parent_id: str,
        experiment: str | None = None,
    ) -> None:
        self.cfg = cfg
        self.experiment = experiment
        self.space = space
        self.metric = str(search.metric)
        self.monitor = str(search.get("monitor") or "val/loss")
        self.trials_dir = trials_dir
        self.parent_id = parent_id

    def __call__(self, trial: optuna.Trial) -> float:
        """Train the trial's config; return its metric (``hparams_search.metric``)."""
        values = {p.key: p.suggest(trial) for p in self.space}
        trial_dir = self.trials_dir / f"trial_{trial.number:04d}"
        tcfg = trial_config(self.cfg, values, trial_dir, self.monitor, self.experiment)
        trial.set_user_attr("trial_dir", str(trial_dir))
        trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
        name = f"study:{trial.study.study_name}"
        try:
            with active_trial(trial), parent_run(self.parent_id, name):
                metrics, _ = train(read_training(tcfg))
        except optuna.TrialPruned:
            steps = trial.storage.get_trial(trial._trial_id).intermediate_values
            trial.set_user_attr("pruned_at_epoch", max(steps) if steps else None)
            self._end_run(trial, "PRUNED", "KILLED")
            raise
        except BaseException:
            self._end_run(trial, "FAIL", None)  # the failed run already ended FAILED
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
