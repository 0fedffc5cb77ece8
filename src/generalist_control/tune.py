"""Optuna search of the training's hyper-parameters: ``python tune.py [overrides]``.

``python tune.py`` (also ``gc-tune``, ``python -m generalist_control.tune``) composes the
primary config (``conf/tune.yaml`` = ``conf/config.yaml`` + ``hparams_search: default``)
and runs a named Optuna study in RDB storage (``hparams_search.storage``, default
``sqlite:///optuna.db``; ``postgresql+psycopg2://...`` for many workers). Every trial sets
its sampled values on a copy of the config (the keys that the tree ``hparams_search.params``
leads to, e.g. ``model.hidden``) and calls :func:`generalist_control.train.train`; the
objective is ``metrics[hparams_search.metric]`` (``val/loss``). See docs/sweeps.md.

* **Resuming and several workers.** The study is loaded if it exists, so re-running the
  command (on any machine that reaches the storage) adds ``n_trials`` more trials to it;
  ``max_trials`` caps the study's finished trials over all workers and runs.
* **Pruning.** :class:`OptunaPruning`, a Lightning callback added to each trial's trainer,
  reports ``val/loss`` after every epoch's validation and raises :class:`optuna.TrialPruned`
  when the pruner says so.
* **Killed workers.** The storage records a heartbeat of every running trial
  (``hparams_search.heartbeat``); a trial whose heartbeat is older than the grace period
  is set to ``FAIL`` by the next worker (on start and before each trial), and its MLflow
  run to ``FAILED``; the study goes on.
* **MLflow.** Each trial is one MLflow training run, tagged ``optuna.study`` and
  ``optuna.trial`` and nested under the study's parent run (its id is kept in the study's
  user attribute ``mlflow_parent_run_id``); pruned trials' runs end ``KILLED``. Each trial
  writes its checkpoints and model under ``<trials_dir>/trial_<n>``, never to the DVC
  output ``models/``.
"""

from __future__ import annotations

import copy
import difflib
import json
import logging
import math
import os
import random
import socket
import time
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import mlflow
import optuna
import sqlalchemy
from hydra.core.hydra_config import HydraConfig
from lightning.pytorch.trainer.states import TrainerFn
from mlflow.exceptions import MlflowException
from omegaconf import DictConfig, OmegaConf, open_dict
from optuna.trial import FrozenTrial, TrialState

from generalist_control import mlflow_utils
from generalist_control.paths import HYDRA_CONFIG_PATH
from generalist_control.sweep import ROLE_TAG, create_parent_run, parent_run

__all__ = [
    "OptunaPruning",
    "Param",
    "main",
    "open_storage",
    "parse_space",
    "run",
    "trial_config",
]

log = logging.getLogger(__name__)

#: Study user attribute holding the id of the study's MLflow parent run.
PARENT_ATTR = "mlflow_parent_run_id"
_FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)
_CREATE_ATTEMPTS = 5
_BACKENDS = ("sqlite", "postgresql", "mysql")
_SPEC_KEYS = {
    "categorical": {"type", "choices"},
    "int": {"type", "low", "high", "step", "log"},
    "float": {"type", "low", "high", "step", "log"},
}

#: The trial being evaluated (set around ``train(cfg)``; read by :class:`OptunaPruning`,
#: which ``train`` instantiates from the config and so cannot receive the trial itself).
_ACTIVE_TRIAL: list[optuna.Trial] = []


# --------------------------------------------------------------------------- search space
@dataclass(frozen=True)
class Param:
    """One dimension of the search space: a config key and its distribution.

    Parameters
    ----------
    key : str
        Dotted config key, e.g. ``model.hidden`` (also the Optuna parameter name).
    type : {"categorical", "int", "float"}
        The distribution.
    choices : tuple, optional
        Values of a categorical parameter.
    low, high : float, optional
        Bounds of an int or float parameter (both included).
    step : float, optional
        Grid step of an int or float parameter.
    log : bool
        Sample on a log scale (int and float).
    """

    key: str
    type: str
    choices: tuple[Any, ...] | None = None
    low: float | None = None
    high: float | None = None
    step: float | None = None
    log: bool = False

    def suggest(self, trial: optuna.Trial) -> Any:
        """Draw this parameter's value for ``trial``."""
        if self.type == "categorical":
            return trial.suggest_categorical(self.key, list(self.choices or ()))
        if self.type == "int":
            step = int(self.step) if self.step else 1
            return trial.suggest_int(
                self.key, int(self.low), int(self.high), step=step, log=self.log
            )
        return trial.suggest_float(
            self.key, float(self.low), float(self.high), step=self.step, log=self.log
        )


def parse_space(params: Mapping[str, Any], cfg: DictConfig) -> list[Param]:
    """Validate ``hparams_search.params`` against the config; return the search space.

    Parameters
    ----------
    params : mapping
        The config's tree down to the searched keys, each ending in a distribution (a
        mapping with a ``type``): ``{model: {hidden: {type: categorical, choices: [...]}}}``
        searches ``model.hidden``.
    cfg : DictConfig
        The composed config the trials modify: every key must name a value in it.

    Raises
    ------
    KeyError
        A key that the config does not have (with the closest existing keys).
    ValueError
        An empty space, a key naming a config section, or a malformed distribution.
    """
    specs = _specs(params, "")
    if not specs:
        raise ValueError("hparams_search.params is empty: nothing to search")
    space = []
    leaves = None
    for key, spec in specs.items():
        node = OmegaConf.select(cfg, key, default=KeyError)
        if node is KeyError:
            if leaves is None:
                leaves = _leaf_keys(cfg)
            close = difflib.get_close_matches(key, leaves, n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise KeyError(f"unknown search-space key {key!r}: the config has no such key{hint}")
        if OmegaConf.is_config(node):
            raise ValueError(f"search-space key {key!r} names a config section, not a value")
        space.append(_param(key, spec))
    return space


def _specs(node: Any, prefix: str) -> dict[str, Any]:
    """``{dotted key: distribution}`` from the nested ``params`` tree."""
    if node is None:
        return {}
    if not isinstance(node, Mapping) and not OmegaConf.is_dict(node):
        raise ValueError(
            f"hparams_search.params.{prefix} must be a distribution (a mapping with a "
            f"'type') or a mapping of them, not {node!r}"
        )
    if "type" in node:
        return {prefix: node}
    out: dict[str, Any] = {}
    for key, value in node.items():
        out.update(_specs(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def _leaf_keys(cfg: DictConfig) -> list[str]:
    container = OmegaConf.to_container(cfg, resolve=False)
    return list(mlflow_utils.flatten_params(container, exclude=()))


def _param(key: str, spec: Any) -> Param:
    where = f"hparams_search.params.{key}"
    if not isinstance(spec, Mapping) and not OmegaConf.is_dict(spec):
        raise ValueError(f"{where} must be a mapping with a 'type', not {spec!r}")
    spec = dict(spec)
    kind = spec.get("type")
    if kind not in _SPEC_KEYS:
        raise ValueError(f"{where}.type must be one of {sorted(_SPEC_KEYS)}, not {kind!r}")
    extra = set(spec) - _SPEC_KEYS[kind]
    if extra:
        raise ValueError(f"{where}: unknown field(s) {sorted(extra)} for type {kind!r}")
    if kind == "categorical":
        choices = spec.get("choices")
        if not choices or isinstance(choices, str):
            raise ValueError(f"{where}.choices must be a non-empty list")
        return Param(key, kind, choices=tuple(choices))
    low, high = spec.get("low"), spec.get("high")
    if low is None or high is None or not low < high:
        raise ValueError(f"{where} needs low < high, got low={low!r}, high={high!r}")
    log_scale = bool(spec.get("log", False))
    if log_scale and low <= 0:
        raise ValueError(f"{where}: a log-scale range needs low > 0, got {low!r}")
    return Param(key, kind, low=low, high=high, step=spec.get("step"), log=log_scale)


# ------------------------------------------------------------------------------- storage
def _describe(url: str) -> str:
    """The URL with its password hidden (for logs and tags)."""
    try:
        return sqlalchemy.engine.make_url(url).render_as_string(hide_password=True)
    except sqlalchemy.exc.ArgumentError:
        return "<unparsable URL>"


def open_storage(
    url: str,
    heartbeat: Mapping[str, Any] | None = None,
    on_stale_trial: Any | None = None,
) -> optuna.storages.RDBStorage:
    """Open (and create the tables of) the Optuna RDB storage at ``url``.

    Parameters
    ----------
    url : str
        SQLAlchemy URL: ``sqlite:///optuna.db`` (relative to the working directory),
        ``postgresql+psycopg2://user:password@host:5432/db``, or a MySQL URL.
    heartbeat : mapping, optional
        ``interval`` and ``grace_period`` (positive whole seconds); ``interval`` null
        turns the heartbeat (and the failing of dead workers' trials) off.
    on_stale_trial : callable, optional
        Called with ``(study, trial)`` for each trial the heartbeat check sets to ``FAIL``.

    Raises
    ------
    ValueError
        An unparsable URL or an unsupported database.
    ConnectionError
        The database cannot be reached or opened.
    """
    example = "e.g. sqlite:///optuna.db or postgresql+psycopg2://user:password@host:5432/optuna"
    try:
        parsed = sqlalchemy.engine.make_url(str(url))
    except sqlalchemy.exc.ArgumentError as e:
        raise ValueError(f"bad Optuna storage URL {url!r}: not a database URL ({example})") from e
    backend = parsed.get_backend_name()
    if backend not in _BACKENDS:
        hint = " (write postgresql://, not postgres://)" if backend == "postgres" else ""
        raise ValueError(
            f"bad Optuna storage URL {_describe(url)!r}: database {backend!r} is not one of "
            f"{', '.join(_BACKENDS)}{hint}; {example}"
        )
    if backend == "sqlite" and parsed.database not in (None, "", ":memory:"):
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    hb = dict(heartbeat or {})
    interval = hb.get("interval")
    kwargs: dict[str, Any] = {}
    if interval:
        kwargs = {
            "heartbeat_interval": int(interval),
            "grace_period": int(hb["grace_period"]) if hb.get("grace_period") else None,
            "heartbeat_stale_trial_callback": on_stale_trial,
        }
    engine_kwargs = {} if backend == "sqlite" else {"pool_pre_ping": True}
    where = _describe(url)
    for attempt in range(1, _CREATE_ATTEMPTS + 1):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                return optuna.storages.RDBStorage(str(url), engine_kwargs=engine_kwargs, **kwargs)
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError) as e:
            # workers that start together on an empty database race to create the tables:
            # the loser sees "already exists" and tries again
            if attempt == _CREATE_ATTEMPTS:
                raise ConnectionError(f"cannot create the Optuna tables in {where}: {e}") from e
            time.sleep(0.5 * attempt + random.random())
        except (sqlalchemy.exc.SQLAlchemyError, ImportError) as e:
            reason = str(getattr(e, "orig", None) or e).strip()
            raise ConnectionError(f"cannot open the Optuna storage {where}: {reason}") from e
    raise AssertionError("unreachable")


class _StaleTrialHandler:
    """Heartbeat-stale trial (its worker died): log it, end its MLflow run, maybe retry."""

    def __init__(self, logger: Mapping[str, Any], max_retry: int) -> None:
        self.logger = dict(logger)
        self.max_retry = int(max_retry or 0)

    def __call__(self, study: optuna.Study, trial: FrozenTrial) -> None:
        log.warning(
            "trial %d of study %r lost its worker (no heartbeat within the grace period): FAIL",
            trial.number,
            study.study_name,
        )
        run_id = trial.user_attrs.get("mlflow_run_id")
        if run_id:
            try:
                mlflow_utils.set_tracking(self.logger)
                client = mlflow.MlflowClient()
                client.set_tag(run_id, "optuna.state", "FAIL")
                client.set_terminated(run_id, "FAILED")
            except MlflowException as e:  # the run lives in another store
                log.warning("could not end MLflow run %s of trial %d: %s", run_id, trial.number, e)
        if self.max_retry > 0:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                retry = optuna.storages.RetryHeartbeatStaleTrialCallback(self.max_retry)
            retry(study, trial)


def _fail_stale_trials(study: optuna.Study) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        optuna.storages.fail_stale_trials(study)


# ------------------------------------------------------------------------------- trials
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
        value = trainer.callback_metrics.get(self.monitor)
        if value is None:
            raise KeyError(f"OptunaPruning: no logged metric {self.monitor!r} to report")
        value, epoch = float(value), int(trainer.current_epoch)
        self.trial.report(value, step=epoch)
        if self.trial.should_prune():
            self.trial.set_user_attr("pruned_at_epoch", epoch)
            self.trial.set_user_attr("pruned_by", type(self).__name__)
            raise optuna.TrialPruned(f"pruned at epoch {epoch}: {self.monitor} = {value:.6g}")


def trial_config(
    cfg: DictConfig, values: Mapping[str, Any], trial_dir: Path, monitor: str = "val/loss"
) -> DictConfig:
    """The training config of one trial: ``cfg`` with ``values`` set, outputs in ``trial_dir``.

    The search's own section (``hparams_search``) is dropped, the checkpoints go to
    ``<trial_dir>/run`` and the model to ``<trial_dir>/models``, and :class:`OptunaPruning`
    is added to the callbacks.
    """
    tcfg = copy.deepcopy(cfg)
    with open_dict(tcfg):
        tcfg.pop("hparams_search", None)
        for key, value in values.items():
            OmegaConf.update(tcfg, key, value, merge=False)
        tcfg.run_dir = str(trial_dir / "run")
        tcfg.paths.models_dir = str(trial_dir / "models")
        if tcfg.get("callbacks") is None:
            tcfg.callbacks = {}
        tcfg.callbacks.optuna_pruning = {
            "_target_": f"{__name__}.OptunaPruning",
            "monitor": monitor,
        }
    return tcfg


@contextmanager
def _active(trial: optuna.Trial) -> Iterator[None]:
    _ACTIVE_TRIAL.append(trial)
    try:
        yield
    finally:
        _ACTIVE_TRIAL.remove(trial)


class _Objective:
    """Train one trial's config; return its metric."""

    def __init__(
        self,
        cfg: DictConfig,
        space: list[Param],
        search: DictConfig,
        trials_dir: Path,
        parent_id: str,
    ) -> None:
        self.cfg = cfg
        self.space = space
        self.metric = str(search.metric)
        self.monitor = str(search.get("monitor") or "val/loss")
        self.trials_dir = trials_dir
        self.parent_id = parent_id

    def __call__(self, trial: optuna.Trial) -> float:
        from generalist_control.train import train  # heavy; only when a trial runs

        values = {p.key: p.suggest(trial) for p in self.space}
        trial_dir = self.trials_dir / f"trial_{trial.number:04d}"
        tcfg = trial_config(self.cfg, values, trial_dir, self.monitor)
        trial.set_user_attr("trial_dir", str(trial_dir))
        trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
        name = f"study:{trial.study.study_name}"
        try:
            with _active(trial), parent_run(self.parent_id, name):
                metrics, _ = train(tcfg)
        except optuna.TrialPruned:
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


# ------------------------------------------------------------------------------ the study
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


def _study_parent(study: optuna.Study, logger: Mapping[str, Any], storage: str) -> str:
    """The study's MLflow parent run, reopened as ``RUNNING``; created on first use.

    The parent is the oldest active run of the experiment tagged as this study's
    (``gc.role=study``, ``optuna.study``, ``optuna.storage``): workers that start together
    and both create one agree on the older, and the other is deleted. Its id is also kept
    in the study's user attribute ``mlflow_parent_run_id``.
    """
    exp_id = mlflow_utils.experiment_id(logger)
    client = mlflow.MlflowClient()
    query = f"tags.`{ROLE_TAG}` = 'study' and tags.`optuna.study` = '{study.study_name}'"

    def oldest() -> str | None:
        runs = client.search_runs([exp_id], filter_string=query, max_results=1000)
        runs = [r for r in runs if r.data.tags.get("optuna.storage") == storage]
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
        metrics["study/best_value"] = float(best.value)
        tags = {
            "study.best_trial": str(best.number),
            "study.best_params": json.dumps(best.params)[:5000],
        }
        if best.user_attrs.get("mlflow_run_id"):
            tags["study.best_run_id"] = best.user_attrs["mlflow_run_id"]
        for key, value in tags.items():
            _shared_write(client.set_tag, parent_id, key, value)
    for key, value in metrics.items():
        _shared_write(client.log_metric, parent_id, key, value)
    _shared_write(client.set_terminated, parent_id, status)
    return summary


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
    ConnectionError
        The storage cannot be opened.
    """
    search = cfg.get("hparams_search")
    if search is None:
        raise ValueError("no search configured: choose one, e.g. hparams_search=default")
    space = parse_space(search.get("params") or {}, cfg)
    n_trials = int(search.n_trials)
    max_trials = search.get("max_trials")
    if n_trials < 0 or (max_trials is not None and int(max_trials) < 0):
        raise ValueError("hparams_search.n_trials and max_trials must not be negative")
    if not str(search.study_name) or any(c in str(search.study_name) for c in "'\"`"):
        raise ValueError(
            f"hparams_search.study_name must be non-empty, without quotes: {search.study_name!r}"
        )
    direction = str(search.get("direction", "minimize"))
    if direction not in ("minimize", "maximize"):
        raise ValueError(f"hparams_search.direction must be minimize or maximize: {direction!r}")
    # resolve once: the trials' configs must not depend on the search section they drop
    search = OmegaConf.create(OmegaConf.to_container(search, resolve=True))
    pruner = _pruner(search)  # a bad sampler or pruner fails before the storage is touched
    _sampler(search, 0)
    heartbeat = search.get("heartbeat") or {}
    handler = _StaleTrialHandler(cfg.logger, heartbeat.get("max_retry") or 0)
    storage = open_storage(str(search.storage), heartbeat, handler)
    url = _describe(str(search.storage))

    study = optuna.create_study(
        storage=storage,
        study_name=str(search.study_name),
        direction=direction,
        load_if_exists=True,
    )
    if study.direction.name.lower() != direction:
        raise ValueError(
            f"study {study.study_name!r} in {url} exists with direction "
            f"{study.direction.name.lower()}, not {direction}"
        )
    _fail_stale_trials(study)  # dead workers' trials end FAIL before anything else
    n_existing = len(study.get_trials(deepcopy=False))
    study.sampler = _sampler(search, n_existing)
    study.pruner = pruner
    if max_trials is not None:
        done = len(study.get_trials(deepcopy=False, states=_FINISHED))
        n_trials = max(0, min(n_trials, int(max_trials) - done))
    log.info(
        "study %r in %s: %d trials so far, adding up to %d",
        study.study_name,
        url,
        n_existing,
        n_trials,
    )
    parent_id = _study_parent(study, cfg.logger, url)
    objective = _Objective(cfg, space, search, _trials_dir(search), parent_id)
    callbacks = []
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
            )
        status = "FINISHED"
    finally:
        mlflow_utils.set_tracking(cfg.logger)
        summary = _summarise(study, parent_id, status)
        log.info("study %r: %s", study.study_name, summary)
    return study


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="tune")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: run the study; return its best value (NaN if none completed)."""
    study = run(cfg)
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    return float(study.best_value) if complete else math.nan


if __name__ == "__main__":
    main()
