"""Optuna search of the training's hyper-parameters (``python tune.py``; see docs/sweeps.md).

:func:`run` takes the composed config of ``conf/tune.yaml`` (``conf/config.yaml`` +
``hparams_search: default``) and runs a named Optuna study in RDB storage
(``hparams_search.storage``, default ``sqlite:///optuna.db``; ``postgresql+psycopg2://...``
for many workers). Every trial sets its sampled values on a copy of the config (the keys
that the tree ``hparams_search.params`` leads to, e.g. ``model.hidden``) and trains it
(:class:`~generalist_control.sweeps.trials.Objective`).

* **Resuming and several workers.** The study is loaded if it exists, so re-running the
  command (on any machine that reaches the storage) adds ``n_trials`` more trials to it;
  ``max_trials`` caps the study's finished trials over all workers and runs.
* **One fixed config per study.** The part of the config that shapes a trial apart from
  the searched keys is recorded when the study is created; resuming it under another one
  (e.g. ``trainer.max_epochs=60`` after a 1-epoch study) is refused, naming the changed
  keys (:mod:`~generalist_control.sweeps.fixed`).
* **Pruning.** optuna-integration's ``PyTorchLightningPruningCallback``
  (:class:`~generalist_control.sweeps.pruning.FitPruning`), added to each trial's trainer,
  reports ``val/loss`` after every epoch's validation and raises
  :class:`optuna.TrialPruned` when the pruner says so.
* **Progress.** One log line per finished trial: its state and value, the best so far
  (``hparams_search.progress_bar=true`` adds Optuna's progress bar).
* **Killed workers.** The storage records a heartbeat of every running trial
  (``hparams_search.heartbeat``); a trial whose heartbeat is older than the grace period
  is set to ``FAIL`` by the next worker (on start and before each trial), and its MLflow
  run to ``FAILED``; the study goes on.
* **MLflow.** The study and its trials go to the experiment of kind ``tune``
  (``<logger.experiment_prefix>/tune``, :mod:`generalist_control.tracking.experiments`).
  Each trial is one MLflow training run, tagged ``optuna.study`` and
  ``optuna.trial`` and nested under the study's parent run (its id is kept in the study's
  user attribute ``mlflow_parent_run_id``); pruned trials' runs end ``KILLED``. Each trial
  writes its checkpoints and model under ``<trials_dir>/trial_<n>``, never to the DVC
  output ``models/``.
"""

from __future__ import annotations

import json
import logging
import random
import re
import time
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path
from typing import Any

import hydra
import mlflow
import optuna
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from optuna.trial import TrialState

from generalist_control.common.configs import as_dict
from generalist_control.common.secrets import redact
from generalist_control.sweeps.fixed import check_fixed_config, fixed_config
from generalist_control.sweeps.space import Param, parse_space
from generalist_control.sweeps.storage import StaleTrialHandler, fail_stale_trials, open_storage
from generalist_control.sweeps.trials import Objective
from generalist_control.tracking import mlflow_utils
from generalist_control.tracking.experiments import experiment_name
from generalist_control.tracking.parents import ROLE_TAG, create_parent_run

__all__ = ["PARENT_ATTR", "PLAIN_NAME", "TrialProgress", "run", "tune_logger"]

log = logging.getLogger(__name__)

#: Study user attribute holding the id of the study's MLflow parent run.
PARENT_ATTR = "mlflow_parent_run_id"
#: A study name: also a folder name (no separator, no ``..``) and an MLflow filter value.
PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
_FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)


def _sampler(search: DictConfig, n_existing: int) -> optuna.samplers.BaseSampler:
    """The sampler, its seed offset by the study's trial count and the worker number.

    A fresh single-worker study with seed ``s`` is reproducible; a resumed study and a
    second worker draw new values instead of repeating the first ones.
    """
    node = search.get("sampler")
    if node is None:
        return optuna.samplers.TPESampler()
    kwargs = {}
    if node.get("seed") is not None:
        kwargs["seed"] = int(node.seed) + n_existing + 1000 * int(search.get("worker") or 0)
    return hydra.utils.instantiate(node, **kwargs)


def _pruner(search: DictConfig) -> optuna.pruners.BasePruner:
    node = search.get("pruner")
    return optuna.pruners.NopPruner() if node is None else hydra.utils.instantiate(node)


def _trials_dir(search: DictConfig) -> Path:
    if search.get("trials_dir"):
        return Path(search.trials_dir)
    if HydraConfig.initialized():
        base = Path(HydraConfig.get().runtime.output_dir)
    else:
        base = Path("outputs/tune") / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    return base / str(search.study_name)


def tune_logger(logger: Mapping[str, Any]) -> dict[str, Any]:
    """The ``logger`` config with the experiment of kind ``tune`` named explicitly.

    The study's parent run and its trials' training runs all go there.
    """
    plain = as_dict(logger)
    return {**plain, "experiment_name": experiment_name(plain, "tune")}


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


def _checked_search(cfg: DictConfig) -> DictConfig:
    """``cfg.hparams_search``, checked and resolved (before anything is opened or written)."""
    search = cfg.get("hparams_search")
    if search is None:
        raise ValueError("no search configured: choose one, e.g. hparams_search=default")
    max_trials = search.get("max_trials")
    if int(search.n_trials) < 0 or (max_trials is not None and int(max_trials) < 0):
        raise ValueError("hparams_search.n_trials and max_trials must not be negative")
    if not PLAIN_NAME.fullmatch(str(search.study_name)):
        raise ValueError(
            f"hparams_search.study_name = {str(search.study_name)!r} is not a plain name: it "
            "also names the folder of the study's trials (<trials_dir>/<study_name>), which "
            "must stay in trials_dir; use letters, digits, '.', '_' and '-', starting with a "
            "letter or digit, e.g. generalist-control-v2"
        )
    direction = str(search.get("direction", "minimize"))
    if direction not in ("minimize", "maximize"):
        raise ValueError(f"hparams_search.direction must be minimize or maximize: {direction!r}")
    # resolve once: the trials' configs must not depend on the search section they drop
    return OmegaConf.create(as_dict(search))


def _open_study(cfg: DictConfig, search: DictConfig) -> optuna.Study:
    """Create or load the study, fail dead workers' trials, set its sampler and pruner."""
    pruner = _pruner(search)  # a bad sampler or pruner fails before the storage is touched
    _sampler(search, 0)
    heartbeat = search.get("heartbeat") or {}
    handler = StaleTrialHandler(cfg.logger, heartbeat.get("max_retry") or 0)
    storage = open_storage(str(search.storage), heartbeat, handler)
    direction: Any = str(search.get("direction", "minimize"))
    study = optuna.create_study(
        storage=storage,
        study_name=str(search.study_name),
        direction=direction,
        load_if_exists=True,
    )
    if study.direction.name.lower() != direction:
        raise ValueError(
            f"study {study.study_name!r} in {redact(str(search.storage))} exists with "
            f"direction {study.direction.name.lower()}, not {direction}"
        )
    fail_stale_trials(study)  # dead workers' trials end FAIL before anything else
    study.sampler = _sampler(search, len(study.get_trials(deepcopy=False)))
    study.pruner = pruner
    return study


def _open_checked(cfg: DictConfig, search: DictConfig, space: list[Param]) -> optuna.Study:
    """:func:`_open_study`, then its fixed config recorded or checked (``sweeps.fixed``)."""
    fixed = fixed_config(cfg, [p.key for p in space], list(search.get("identity_keys") or []))
    study = _open_study(cfg, search)
    check_fixed_config(study, fixed, bool(search.get("allow_config_change")))
    return study


def _trials_to_add(study: optuna.Study, search: DictConfig) -> int:
    """``n_trials``, capped so the study ends with at most ``max_trials`` finished trials."""
    n_trials, max_trials = int(search.n_trials), search.get("max_trials")
    if max_trials is None:
        return n_trials
    done = len(study.get_trials(deepcopy=False, states=_FINISHED))
    return max(0, min(n_trials, int(max_trials) - done))


def run(cfg: DictConfig) -> optuna.Study:
    """Run (or continue) the study configured by ``cfg.hparams_search``; return it.

    Parameters
    ----------
    cfg : DictConfig
        The composed config of ``conf/tune.yaml`` (or ``config.yaml`` with an
        ``hparams_search`` group chosen).

    Returns
    -------
    optuna.Study
        The study, loaded from its storage with every worker's trials.

    Raises
    ------
    ValueError, KeyError
        No or a malformed search configuration (checked before anything is written).
    StudyConfigChangedError
        The study exists with another fixed config (:mod:`~generalist_control.sweeps.fixed`)
        and ``hparams_search.allow_config_change`` is false; no trial is run.
    ConnectionError
        The storage cannot be opened.
    """
    search = _checked_search(cfg)
    space = parse_space(search.get("params") or {}, cfg)
    study = _open_checked(cfg, search, space)
    n_trials = _trials_to_add(study, search)
    url = redact(str(search.storage))
    n_existing = len(study.get_trials(deepcopy=False))
    log.info(
        "study %r in %s: %d trials so far, adding up to %d",
        study.study_name, url, n_existing, n_trials,
    )  # fmt: skip
    logger = tune_logger(cfg.logger)
    parent_id = _study_parent(study, logger, url)
    trials_dir = _trials_dir(search)
    objective = Objective(cfg, space, search, trials_dir, parent_id, logger["experiment_name"])
    max_trials = search.get("max_trials")
    callbacks: list[Any] = [TrialProgress(n_trials)]
    if max_trials is not None:
        callbacks.append(optuna.study.MaxTrialsCallback(int(max_trials), states=_FINISHED))
    status = "FAILED"
    try:
        if n_trials:
            study.optimize(
                objective,
                n_trials=n_trials,
                timeout=search.get("timeout"),
                callbacks=callbacks,
                gc_after_trial=True,
                show_progress_bar=bool(search.get("progress_bar")),
            )
        status = "FINISHED"
    finally:
        mlflow_utils.set_tracking(logger)
        summary = _summarise(study, parent_id, status)
        log.info("study %r: %s", study.study_name, summary)
    return study
