"""Optuna's RDB storage: opening it (workers racing to create tables), and dead workers' trials."""

from __future__ import annotations

import logging
import random
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import mlflow
import optuna
import sqlalchemy
from mlflow.exceptions import MlflowException
from optuna.trial import FrozenTrial

from generalist_control.common.secrets import redact
from generalist_control.sweeps.search_settings import HeartbeatSettings
from generalist_control.tracking import mlflow_utils

__all__ = ["end_trial_run", "fail_lost_trial", "open_storage"]

log = logging.getLogger(__name__)

_CREATE_ATTEMPTS = 5
_BACKENDS = ("sqlite", "postgresql", "mysql")
_EXAMPLE = "e.g. sqlite:///optuna.db or postgresql+psycopg2://user:password@host:5432/optuna"


def _parse(url: str) -> sqlalchemy.engine.URL:
    """The parsed storage URL; a clear error for a bad URL or an unsupported database."""
    try:
        parsed = sqlalchemy.engine.make_url(str(url))
    except sqlalchemy.exc.ArgumentError as e:
        raise ValueError(
            f"bad Optuna storage URL {redact(url)!r}: not a database URL ({_EXAMPLE})"
        ) from e
    backend = parsed.get_backend_name()
    if backend not in _BACKENDS:
        hint = " (write postgresql://, not postgres://)" if backend == "postgres" else ""
        raise ValueError(
            f"bad Optuna storage URL {redact(url)!r}: database {backend!r} is not one of "
            f"{', '.join(_BACKENDS)}{hint}; {_EXAMPLE}"
        )
    return parsed


def open_storage(
    url: str,
    heartbeat: HeartbeatSettings | None = None,
    on_stale_trial: Callable[[optuna.Study, FrozenTrial], None] | None = None,
) -> optuna.storages.RDBStorage:
    """Open (and create the tables of) the Optuna RDB storage at ``url``.

    ``url``: SQLite, PostgreSQL or MySQL. ``heartbeat`` None, or its ``interval`` None: dead
    workers' trials are never failed; else ``on_stale_trial(study, trial)`` is called for
    each trial the heartbeat check sets to ``FAIL``.

    Raises
    ------
    ValueError
        An unparsable URL or an unsupported database.
    ConnectionError
        The database cannot be reached or opened.
    """
    parsed = _parse(url)
    backend = parsed.get_backend_name()
    if backend == "sqlite" and parsed.database not in (None, "", ":memory:"):
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    kwargs: dict[str, Any] = {}
    if heartbeat is not None and heartbeat.interval:
        kwargs = {
            "heartbeat_interval": heartbeat.interval,
            "grace_period": heartbeat.grace_period,
            "heartbeat_stale_trial_callback": on_stale_trial,
        }
    engine_kwargs = {} if backend == "sqlite" else {"pool_pre_ping": True}
    where = redact(url)
    for attempt in range(1, _CREATE_ATTEMPTS + 1):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                return optuna.storages.RDBStorage(str(url), engine_kwargs=engine_kwargs, **kwargs)
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError) as e:
            # workers racing to create the tables: the loser tries again
            if attempt == _CREATE_ATTEMPTS:
                raise ConnectionError(f"cannot create the Optuna tables in {where}: {e}") from e
            time.sleep(0.5 * attempt + random.random())
        except (sqlalchemy.exc.SQLAlchemyError, ImportError) as e:
            reason = str(getattr(e, "orig", None) or e).strip()
            raise ConnectionError(f"cannot open the Optuna storage {where}: {reason}") from e
    raise AssertionError("unreachable")


def fail_lost_trial(
    logger: Mapping[str, Any], max_retry: int, study: optuna.Study, trial: FrozenTrial
) -> None:
    """A heartbeat-stale trial (its worker died): log it, fail its MLflow run, maybe retry it."""
    log.warning(
        "trial %d of study %r lost its worker (no heartbeat within the grace period): FAIL",
        trial.number,
        study.study_name,
    )
    end_trial_run(trial, "FAIL", "FAILED", logger)
    if max_retry > 0:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            retry = optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry)
        retry(study, trial)


def end_trial_run(
    trial: optuna.Trial | FrozenTrial,
    state: str,
    status: str | None,
    logger: Mapping[str, Any] | None = None,
) -> None:
    """Tag the trial's MLflow run with the trial's ``state``; set its ``status`` if given.

    ``logger``: the store to point MLflow at first. An MLflow error is only logged: it
    never hides the trial's own outcome (the run may live in another store).
    """
    run_id = trial.user_attrs.get("mlflow_run_id")
    if not run_id:
        return
    try:
        if logger is not None:
            mlflow_utils.set_tracking(logger)
        client = mlflow.MlflowClient()
        client.set_tag(run_id, "optuna.state", state)
        if status:
            client.set_terminated(run_id, status)
    except MlflowException as e:
        log.warning("could not update MLflow run %s of trial %d: %s", run_id, trial.number, e)
