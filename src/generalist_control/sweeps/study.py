"""The Optuna study of ``tune.py``: created or resumed in RDB storage, its trials under one parent.

Re-running the command (on any machine that reaches the storage) adds trials to the same
study; the study's MLflow parent run in the experiment of kind ``tune`` groups every
worker's trials; dead workers' trials are failed; SIGTERM or SIGINT fails the running trial,
ends the parent ``KILLED`` and stops (docs/sweeps.md).
"""

from __future__ import annotations

import json
import logging
import random
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
import mlflow
import optuna
from optuna.trial import TrialState

from generalist_control.common.secrets import redact
from generalist_control.sweeps import stop_signals
from generalist_control.sweeps.fixed_config import check_fixed_config
from generalist_control.sweeps.objective import Objective, TrainPoint
from generalist_control.sweeps.search_settings import SearchSettings
from generalist_control.sweeps.search_space import Param
from generalist_control.sweeps.storage import StaleTrialHandler, fail_stale_trials, open_storage
from generalist_control.tracking import mlflow_utils
from generalist_control.tracking.experiments import experiment_name
from generalist_control.tracking.parents import ROLE_TAG, create_parent_run

__all__ = ["PARENT_ATTR", "TrialProgress", "run_study", "tune_logger"]

log = logging.getLogger(__name__)

#: Study user attribute holding the id of the study's MLflow parent run.
PARENT_ATTR = "mlflow_parent_run_id"
_FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)


def _sampler(search: SearchSettings, n_existing: int) -> optuna.samplers.BaseSampler | None:
    """The sampler, its seed offset by the study's trial count and the worker number.

    A fresh single-worker study with seed ``s`` is reproducible; a resumed study and a
    second worker draw new values instead of repeating the first ones.
    """
    node = search.sampler
    if node is None:
        return None  # Optuna's default
    kwargs = {}
    if node.get("seed") is not None:
        kwargs["seed"] = int(node["seed"]) + n_existing + 1000 * search.worker
    return hydra.utils.instantiate(node, **kwargs)


def _pruner(search: SearchSettings) -> optuna.pruners.BasePruner:
    node = search.pruner
    return optuna.pruners.NopPruner() if node is None else hydra.utils.instantiate(node)


def tune_logger(logger: Mapping[str, Any]) -> dict[str, Any]:
    """The ``logger`` config with the experiment of kind ``tune`` named explicitly.

    The study's parent run and its trials' training runs all go there.
    """
    return {**logger, "experiment_name": experiment_name(logger, "tune")}


class TrialProgress:
    """Optuna callback: one log line per finished trial, with the best value so far."""

    def __init__(self, n_trials: int) -> None:
        self.n_trials = n_trials
        self.done = 0

    def __call__(self, study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        """Log ``trial <n> (<k>/<n_trials> of this run) <state> value=...; best ...``."""
        self.done += 1
        value = "" if trial.value is None else f" value={trial.value:.6g}"
        complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        best = "none yet"
        if complete:
            top = study.best_trial
            best = f"{top.value:.6g} (trial {top.number}, {top.params})"
        log.info(
            "study %r: trial %d (%d/%d of this run) %s%s; best so far: %s",
            study.study_name, trial.number, self.done, self.n_trials,
            trial.state.name, value, best,
        )  # fmt: skip


def _study_parent(study: optuna.Study, logger: Mapping[str, Any], storage: str) -> str:
    """The study's MLflow parent run, reopened as ``RUNNING``; created on first use.

    The parent is the oldest active run of the experiment tagged as this study's
    (``gc.role=study``, ``optuna.study``, ``optuna.storage``): workers that start together
    and both create one agree on the older, and the other is deleted. Its id is also kept
    in the study's user attribute ``mlflow_parent_run_id``.
    """
    exp_id = mlflow_utils.experiment_id(logger, kind="tune")
    client = mlflow.MlflowClient()
    query = f"tags.`{ROLE_TAG}` = 'study' and tags.`optuna.study` = '{study.study_name}'"

    def oldest() -> str | None:
        found = client.search_runs([exp_id], filter_string=query, max_results=1000)
        runs = [r for r in found if r.data.tags.get("optuna.storage") == storage]
        runs.sort(key=lambda r: (r.info.start_time, r.info.run_id))
        return runs[0].info.run_id if runs else None

    run_id = oldest()
    if run_id is None:
        tags = {"optuna.study": study.study_name, "optuna.storage": storage}
        own = create_parent_run(logger, f"study:{study.study_name}", "study", tags)
        run_id = oldest() or own
        if run_id != own:
            client.delete_run(own)
    client.update_run(run_id, status="RUNNING")
    study.set_user_attr(PARENT_ATTR, run_id)
    return run_id


def _shared_write(call: Any, *args: Any, attempts: int = 6) -> Any:
    """``call(*args)`` on the run that every worker of a study writes to, retried on a clash.

    MLflow's SQL store writes a tag or a latest metric as a read followed by an insert, so
    two workers that end at the same moment can both try the insert, and one of them fails
    with a unique-key violation (seen on PostgreSQL). The retry, after a short random wait,
    finds the row and updates it.
    """
    for attempt in range(attempts):
        try:
            return call(*args)
        except mlflow.exceptions.MlflowException as exc:
            text = str(exc).lower()
            clash = "unique" in text or "duplicate key" in text or "integrity" in text
            if not clash or attempt == attempts - 1:
                raise
            time.sleep(random.uniform(0.05, 0.3) * (attempt + 1))
    return None


def _summarise(study: optuna.Study, parent_id: str, status: str) -> dict[str, Any]:
    """Log the study's state to its parent run and end that run with ``status``.

    Every worker does this when it stops (the last one leaves the final state), so each
    write goes through :func:`_shared_write`.
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
            _shared_write(client.set_tag, parent_id, key, text)
    for key, number in metrics.items():
        _shared_write(client.log_metric, parent_id, key, number)
    _shared_write(client.set_terminated, parent_id, status)
    return summary


def _open_study(search: SearchSettings, logger: Mapping[str, Any]) -> optuna.Study:
    """Create or load the study, fail dead workers' trials, set its sampler and pruner."""
    pruner = _pruner(search)  # a bad sampler or pruner fails before the storage is touched
    _sampler(search, 0)
    handler = StaleTrialHandler(logger, search.heartbeat.max_retry)
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
    fail_stale_trials(study)  # dead workers' trials end FAIL before anything else
    sampler = _sampler(search, len(study.get_trials(deepcopy=False)))
    if sampler is not None:
        study.sampler = sampler
    study.pruner = pruner
    return study


def _trials_to_add(study: optuna.Study, search: SearchSettings) -> int:
    """``n_trials``, capped so the study ends with at most ``max_trials`` finished trials."""
    if search.max_trials is None:
        return search.n_trials
    done = len(study.get_trials(deepcopy=False, states=_FINISHED))
    return max(0, min(search.n_trials, search.max_trials - done))


def _optimize(
    study: optuna.Study,
    objective: Objective,
    search: SearchSettings,
    n_trials: int,
    parent_id: str,
    logger: Mapping[str, Any],
) -> None:
    """Add ``n_trials`` trials (stopping at a signal); log the outcome to the parent run."""
    callbacks: list[Any] = [TrialProgress(n_trials)]
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

    Parameters
    ----------
    search : SearchSettings
        ``hparams_search``.
    space : list of Param
        The search space, checked against the config.
    fixed : mapping
        The study's fixed config (:func:`~generalist_control.sweeps.fixed_config.fixed_config`).
    logger : mapping
        The ``logger`` config naming the study's experiment (:func:`tune_logger`).
    train_point : callable
        ``(values, trial_dir) -> metrics``: one trial's training.
    trials_dir : Path
        Where the trials write (``<trials_dir>/trial_<n>``).

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
    n_trials = _trials_to_add(study, search)
    url = redact(search.storage)
    log.info(
        "study %r in %s: %d trials so far, adding up to %d",
        study.study_name, url, len(study.get_trials(deepcopy=False)), n_trials,
    )  # fmt: skip
    parent_id = _study_parent(study, logger, url)
    objective = Objective(train_point, space, search.metric, trials_dir, parent_id)
    _optimize(study, objective, search, n_trials, parent_id, logger)
    return study
