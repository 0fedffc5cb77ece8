"""A trial's Lightning callbacks: pruning from inside the fit, and the trial-run link.

The config cannot carry the live trial: they take the one :func:`active_trial` set.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import cast

import lightning as L
import optuna
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.trainer.states import TrainerFn
from optuna_integration import PyTorchLightningPruningCallback

__all__ = [
    "FitPruning",
    "TrialRunLink",
    "active_trial",
    "current_trial",
    "trial_pruning",
]

#: The trial being evaluated (set around ``train(cfg)``).
_ACTIVE_TRIAL: list[optuna.Trial] = []


@contextmanager
def active_trial(trial: optuna.Trial) -> Iterator[None]:
    """Within the block, the trial callbacks use ``trial``."""
    _ACTIVE_TRIAL.append(trial)
    try:
        yield
    finally:
        _ACTIVE_TRIAL.remove(trial)


def current_trial() -> optuna.Trial:
    """The trial :func:`active_trial` set; a clear error outside a study."""
    if not _ACTIVE_TRIAL:
        raise RuntimeError("trial callbacks are only used inside an Optuna trial (tune.py)")
    return _ACTIVE_TRIAL[-1]


class FitPruning(PyTorchLightningPruningCallback):
    """optuna-integration's pruning callback, limited to the validations of ``trainer.fit``.

    The library's (5.0) also reports during the ``trainer.validate`` after the fit (the epoch
    twice; a finished trial pruned), and only warns when ``monitor`` is never logged.
    """

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Report and prune as the library does, during the fit only."""
        if trainer.sanity_checking or trainer.state.fn != TrainerFn.FITTING:
            return
        if self.monitor not in trainer.callback_metrics:
            logged = ", ".join(sorted(trainer.callback_metrics)) or "none"
            raise KeyError(
                f"pruning: no logged metric {self.monitor!r} (hparams_search.monitor); "
                f"logged: {logged}"
            )
        super().on_validation_end(trainer, pl_module)


def trial_pruning(monitor: str) -> FitPruning:
    """The pruning callback of the active trial, reporting ``monitor`` after each epoch."""
    return FitPruning(current_trial(), monitor)


class TrialRunLink(L.Callback):
    """Link the trial (``mlflow_run_id``) and its run (tags ``optuna.study``, ``optuna.trial``).

    Takes the active trial (the config cannot name it). optuna-integration's
    ``MLflowCallback`` would open a run of its own per trial instead.
    """

    def __init__(self) -> None:
        self.trial = current_trial()

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Set the trial's ``mlflow_run_id`` and the run's Optuna tags."""
        mlf = cast(MLFlowLogger, trainer.logger)  # the training's (``training_logger``)
        client, run_id = mlf.experiment, str(mlf.run_id)
        self.trial.set_user_attr("mlflow_run_id", run_id)
        client.set_tag(run_id, "optuna.study", self.trial.study.study_name)
        client.set_tag(run_id, "optuna.trial", str(self.trial.number))
