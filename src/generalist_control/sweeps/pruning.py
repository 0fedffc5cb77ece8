"""Pruning a trial from inside its training: a Lightning callback that reports to Optuna."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import lightning as L
import mlflow
import optuna
from lightning.pytorch.trainer.states import TrainerFn

__all__ = ["OptunaPruning", "active_trial"]

#: The trial being evaluated (set around ``train(cfg)``; read by :class:`OptunaPruning`,
#: which ``train`` instantiates from the config and so cannot receive the trial itself).
_ACTIVE_TRIAL: list[optuna.Trial] = []


@contextmanager
def active_trial(trial: optuna.Trial) -> Iterator[None]:
    """Within the block, :class:`OptunaPruning` reports to ``trial``."""
    _ACTIVE_TRIAL.append(trial)
    try:
        yield
    finally:
        _ACTIVE_TRIAL.remove(trial)


class OptunaPruning(L.Callback):
    """Lightning callback: report ``monitor`` to the Optuna trial, prune when told to.

    After each validation of the fit (not the sanity check, not a later
    ``trainer.validate``) the value is reported with the epoch as the step; if the study's
    pruner then prunes the trial, the user attributes ``pruned_at_epoch`` and ``pruned_by``
    are set and :class:`optuna.TrialPruned` is raised, which ends ``trainer.fit`` and the
    trial (state ``PRUNED``). At the start of the fit the trial gets the MLflow run id (user
    attribute ``mlflow_run_id``) and the run the tags ``optuna.study`` and ``optuna.trial``.

    Parameters
    ----------
    monitor : str
        Logged metric to report, e.g. ``val/loss``.
    trial : optuna.Trial, optional
        Default: the trial :func:`run` is evaluating.
    """

    def __init__(self, monitor: str = "val/loss", trial: optuna.Trial | None = None) -> None:
        if trial is None:
            if not _ACTIVE_TRIAL:
                raise RuntimeError("OptunaPruning is only used inside an Optuna trial (tune.py)")
            trial = _ACTIVE_TRIAL[-1]
        self.trial = trial
        self.monitor = monitor

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Link the trial and the active MLflow run both ways."""
        run = mlflow.active_run()
        if run is None:
            return
        self.trial.set_user_attr("mlflow_run_id", run.info.run_id)
        mlflow.set_tags(
            {"optuna.study": self.trial.study.study_name, "optuna.trial": self.trial.number}
        )

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Report the epoch's value; raise :class:`optuna.TrialPruned` if pruned."""
        if trainer.sanity_checking or trainer.state.fn != TrainerFn.FITTING:
            return
        logged = trainer.callback_metrics.get(self.monitor)
        if logged is None:
            raise KeyError(f"OptunaPruning: no logged metric {self.monitor!r} to report")
        value, epoch = float(logged), int(trainer.current_epoch)
        self.trial.report(value, step=epoch)
        if self.trial.should_prune():
            self.trial.set_user_attr("pruned_at_epoch", epoch)
            self.trial.set_user_attr("pruned_by", type(self).__name__)
            raise optuna.TrialPruned(f"pruned at epoch {epoch}: {self.monitor} = {value:.6g}")
