"""The Optuna study of ``tune.py``: created or resumed in RDB storage, its trials under one parent.

Re-running the command (on any machine that reaches the storage) adds trials to the same study;
the study's MLflow parent run groups every worker's trials (docs/sweeps.md).
"""

from __future__ import annotations

import functools
import itertools
import json
import logging
import math
import os
import socket
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import mlflow
import optuna
from optuna.trial import FrozenTrial, TrialState

from generalist_control.common import stop_signals
from generalist_control.common.secrets import redact
from generalist_control.sweeps.search_settings import Param, SearchSettings, check_fixed_config
from generalist_control.sweeps.storage import end_trial_run, fail_lost_trial, open_storage
from generalist_control.sweeps.trial_callbacks import active_trial
from generalist_control.tracking import mlflow_utils
from generalist_control.tracking.mlflow_utils import experiment_name
from generalist_control.tracking.parents import (
    ROLE_TAG,
    create_parent_run,
    find_parents,
    parent_run,
)

__all__ = ["PARENT_ATTR", "Objective", "TrainPoint", "run_study", "tune_logger"]

log = logging.getLogger(__name__)

#: Study user attribute holding the id of the study's MLflow parent run.
PARENT_ATTR = "mlflow_parent_run_id"
_FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)

#: Train the config with ``values`` set, outputs in ``trial_dir``; return its metrics.
TrainPoint = Callable[[Mapping[str, Any], Path], Mapping[str, Any]]


@dataclass(frozen=True)
class Objective:
    """Train one trial's values as one MLflow training run; return its metric.

    ``train_point(values, trial_dir)`` runs inside :func:`active_trial` (so the trial's
    callbacks find the trial) and :func:`parent_run`, in ``<trials_dir>/trial_<number>``;
    ``metric`` is the key of the metrics it returns.
    """

    train_point: TrainPoint
    space: list[Param]
    metric: str
    trials_dir: Path
    parent_id: str

    def __call__(self, trial: optuna.Trial) -> float:
        """Train the trial's values; return its metric."""
        values = {p.key: p.suggest(trial) for p in self.space}
        trial_dir = self.trials_dir / f"trial_{trial.number:04d}"
        trial.set_user_attr("trial_dir", str(trial_dir))
        trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
        parent = f"study:{trial.study.study_name}"
        try:
            with active_trial(trial), parent_run(self.parent_id, parent):
                metrics = self.train_point(values, trial_dir)
        except optuna.TrialPruned:
            steps = trial.storage.get_trial(trial._trial_id).intermediate_values
            trial.set_user_attr("pruned_at_epoch", max(steps) if steps else None)
            end_trial_run(trial, "PRUNED", "KILLED")
            raise
        except BaseException as exc:
            end_trial_run(trial, "FAIL", None)  # its run ended already (FAILED, or KILLED)
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
        end_trial_run(trial, "COMPLETE" if math.isfinite(value) else "FAIL", None)
        return value


def _sampler(search: SearchSettings, n_existing: int) -> optuna.samplers.BaseSampler | None:
    """The sampler, its seed offset by the study's trial count and the worker number.

    A fresh study is reproducible; a resumed one and a second worker draw new values.
    """
    node = search.sampler
    if node is None:
        return None  # Optuna's default
    kwargs = {}
    if node.get("seed") is not None:
        kwargs["seed"] = int(node["seed"]) + n_existing + 1000 * search.worker
    return hydra.utils.instantiate(node, **kwargs)


def tune_logger(logger: Mapping[str, Any]) -> dict[str, Any]:
    """The ``logger`` config naming the experiment of kind ``tune`` (the study's, its trials')."""
    return {**logger, "experiment_name": experiment_name(logger, "tune")}


def _progress(n_trials: int) -> Callable[[optuna.Study, FrozenTrial], None]:
    """Optuna callback: one log line per finished trial, with the best value so far."""
    done = itertools.count(1)

    def report(study: optuna.Study, trial: FrozenTrial) -> None:
        value = "" if trial.value is None else f" value={trial.value:.6g}"
        best = "none yet"
        if study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
            top = study.best_trial
            best = f"{top.value:.6g} (trial {top.number}, {top.params})"
        log.info(
            "study %r: trial %d (%d/%d of this run) %s%s; best so far: %s",
            study.study_name, trial.number, next(done), n_trials, trial.state.name, value, best,
        )  # fmt: skip

    return report


def _oldest_parent(study: optuna.Study, logger: Mapping[str, Any], storage: str) -> str | None:
    """The oldest live run tagged as this study's parent, if any.

    Its tags: ``gc.role=study``, ``optuna.study`` and ``optuna.storage``.
    """
    exp_id = mlflow_utils.experiment_id(logger, kind="tune")
    query = f"tags.`{ROLE_TAG}` = 'study' and tags.`optuna.study` = '{study.study_name}'"
    found = find_parents(mlflow.MlflowClient(), exp_id, query)
    runs = [r for r in found if r.data.tags.get("optuna.storage") == storage]
    return runs[0].info.run_id if runs else None


def _study_parent(study: optuna.Study, logger: Mapping[str, Any], storage: str) -> str:
    """The study's MLflow parent run, reopened as ``RUNNING``; created on first use.

    It is the oldest run tagged as this study's: workers that both create one keep the older
    (and :func:`_settled_parent` mends the case where neither saw the other's yet). Its id is
    kept in the study's user attribute ``mlflow_parent_run_id``.
    """
    run_id = _oldest_parent(study, logger, storage)  # MLflow pointed at logger's store
    client = mlflow.MlflowClient()
    if run_id is None:
        tags = {"optuna.study": study.study_name, "optuna.storage": storage}
        own = create_parent_run(logger, f"study:{study.study_name}", "study", tags)
        run_id = _oldest_parent(study, logger, storage) or own
        if run_id != own:
            client.delete_run(own)
    client.update_run(run_id, status="RUNNING")
    study.set_user_attr(PARENT_ATTR, run_id)
    return run_id


def _settled_parent(
    study: optuna.Study, logger: Mapping[str, Any], storage: str, parent_id: str
) -> str:
    """The study's one parent when a worker stops: ``parent_id``, or the older one.

    Two workers that started together may each have created a parent before the other's was
    visible; the newer one's trial runs then move under the older, and the newer is deleted.
    """
    oldest = _oldest_parent(study, logger, storage)
    if oldest is None or oldest == parent_id:
        return parent_id
    client = mlflow.MlflowClient()
    experiments = [e.experiment_id for e in client.search_experiments()]
    query = f"tags.`mlflow.parentRunId` = '{parent_id}'"
    for child in client.search_runs(experiments, filter_string=query, max_results=10000):
        client.set_tag(child.info.run_id, "mlflow.parentRunId", oldest)
    client.delete_run(parent_id)
    study.set_user_attr(PARENT_ATTR, oldest)
    log.info(
        "study %r: parent run %s merged into the older %s", study.study_name, parent_id, oldest
    )
    return oldest


def _summarise(study: optuna.Study, parent_id: str, status: str) -> dict[str, Any]:
    """Log the study's state to its parent run and end that run with ``status``.

    Every worker does this when it stops (the last one leaves the final state): the writes
    may clash (:func:`~generalist_control.tracking.mlflow_utils.retry_on_clash`).
    """
    trials = study.get_trials(deepcopy=False)
    counts = {s.name.lower(): sum(t.state == s for t in trials) for s in TrialState}
    summary: dict[str, Any] = {"n_trials": len(trials), **counts}
    metrics = {f"study/n_{k}": float(v) for k, v in counts.items()}
    metrics["study/n_trials"] = float(len(trials))
    client = mlflow.MlflowClient()
    if counts["complete"]:
        best = study.best_trial
        summary.update(best_trial=best.number, best_value=best.value, best_params=best.params)
        metrics["study/best_value"] = float(study.best_value)
        tags: dict[str, str] = {
            "study.best_trial": str(best.number),
            "study.best_params": json.dumps(best.params)[:5000],
        }
        if best.user_attrs.get("mlflow_run_id"):
            tags["study.best_run_id"] = best.user_attrs["mlflow_run_id"]
        for key, text in tags.items():
            mlflow_utils.retry_on_clash(client.set_tag, parent_id, key, text)
    for key, number in metrics.items():
        mlflow_utils.retry_on_clash(client.log_metric, parent_id, key, number)
    mlflow_utils.retry_on_clash(client.set_terminated, parent_id, status)
    return summary


def _open_study(search: SearchSettings, logger: Mapping[str, Any]) -> optuna.Study:
    """Create or load the study, fail dead workers' trials, set its sampler and pruner."""
    pruner = optuna.pruners.NopPruner()
    if search.pruner is not None:  # a bad pruner or sampler fails before the storage is opened
        pruner = hydra.utils.instantiate(search.pruner)
    _sampler(search, 0)
    handler = functools.partial(fail_lost_trial, dict(logger), search.heartbeat.max_retry)
    storage = open_storage(search.storage, search.heartbeat, handler)
    direction: Any = search.direction
    study = optuna.create_study(
        storage=storage, study_name=search.study_name, direction=direction, load_if_exists=True
    )
    if study.direction.name.lower() != direction:
        raise ValueError(
            f"study {study.study_name!r} in {redact(search.storage)} exists with "
            f"direction {study.direction.name.lower()}, not {direction}"
        )
    with warnings.catch_warnings():  # dead workers' trials end FAIL before anything else
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        optuna.storages.fail_stale_trials(study)
    sampler = _sampler(search, len(study.get_trials(deepcopy=False)))
    if sampler is not None:
        study.sampler = sampler
    study.pruner = pruner
    return study


def _optimize(
    study: optuna.Study,
    objective: Objective,
    search: SearchSettings,
    n_trials: int,
    logger: Mapping[str, Any],
    storage: str,
) -> None:
    """Add ``n_trials`` trials (stopping at a signal); log the outcome to the parent run."""
    callbacks: list[Any] = [_progress(n_trials)]
    if search.max_trials is not None:
        callbacks.append(optuna.study.MaxTrialsCallback(search.max_trials, states=_FINISHED))
    status = "FAILED"
    try:
        with stop_signals.stopping_on_signals():
            if n_trials:
                study.optimize(
                    objective,
                    n_trials=n_trials,
                    timeout=search.timeout,
                    callbacks=callbacks,
                    gc_after_trial=True,
                    show_progress_bar=search.progress_bar,
                )
            status = "FINISHED"
    finally:
        if stop_signals.received() is not None:
            status = "KILLED"
        mlflow_utils.set_tracking(logger)
        parent_id = _settled_parent(study, logger, storage, objective.parent_id)
        summary = _summarise(study, parent_id, status)
        log.info("study %r: %s", study.study_name, summary)


def run_study(
    search: SearchSettings,
    space: list[Param],
    fixed: Mapping[str, str],
    logger: Mapping[str, Any],
    train_point: TrainPoint,
    trials_dir: Path,
) -> optuna.Study:
    """Run (or continue) the study; return it, loaded with every worker's trials.

    ``fixed``: the study's fixed config; ``logger`` names its experiment (:func:`tune_logger`);
    ``train_point`` trains one trial in ``<trials_dir>/trial_<n>``.

    Raises
    ------
    StudyConfigChangedError
        The study exists with another fixed config and ``allow_config_change`` is false; no
        trial is run and MLflow is not touched.
    ConnectionError
        The storage cannot be opened.
    """
    study = _open_study(search, logger)
    check_fixed_config(study, fixed, search.allow_config_change)
    n_trials = search.n_trials  # capped: at most max_trials finished trials in the study
    if search.max_trials is not None:
        done = len(study.get_trials(deepcopy=False, states=_FINISHED))
        n_trials = max(0, min(n_trials, search.max_trials - done))
    url = redact(search.storage)
    log.info(
        "study %r in %s: %d trials so far, adding up to %d",
        study.study_name, url, len(study.get_trials(deepcopy=False)), n_trials,
    )  # fmt: skip
    parent_id = _study_parent(study, logger, url)
    objective = Objective(train_point, space, search.metric, trials_dir, parent_id)
    _optimize(study, objective, search, n_trials, logger, url)
    return study
