"""MLflow: the store, its experiments (one per kind of work), runs other than training, safety.

The default store is SQLite (``mlflow.db``); a fresh one is initialised under a file lock,
params are redacted, and a run whose process is gone is ended by the next run. Experiments are
named ``<logger.experiment_prefix>/<kind>`` (docs/sweeps.md) and tagged as model development,
so that ``mlflow ui`` opens them on their runs, not on MLflow's GenAI overview.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import random
import socket
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from generalist_control.common.atomic import pid_alive, process_start
from generalist_control.common.secrets import redact
from generalist_control.common.sections import ConfigTree

if TYPE_CHECKING:
    import mlflow

__all__ = [
    "DEFAULT_PREFIX",
    "KINDS",
    "KIND_TAG",
    "PARENT_RUN_ENV",
    "POLICY_HASH_TAG",
    "SWEEP_ENV",
    "check_store",
    "dvc_data_version",
    "end_stale_runs",
    "experiment_id",
    "experiment_name",
    "find_training_run",
    "flatten_params",
    "init_store",
    "mlflow_run",
    "now",
    "parent_run_tags",
    "process_tags",
    "retry_on_clash",
    "set_tracking",
    "store_lock",
    "swap_env",
    "tag_kind",
    "tracking_uri",
]

log = logging.getLogger(__name__)

DEFAULT_PREFIX = "generalist-control"
#: The kinds of work, each with its own experiment.
KINDS = (
    "train", "sweep", "tune", "report", "ablation", "tag-free", "variants", "adapt", "unseen",
    "evaluate",
)  # fmt: skip
#: MLflow 3's experiment type tag and its value for model training (not GenAI).
KIND_TAG = ("mlflow.experimentKind", "custom_model_development")
#: The tag that names the policy file a run wrote, by its hash: a policy file holds no run id,
#: so that the same training writes the same bytes (and ``dvc repro`` keeps ``dvc.lock``).
POLICY_HASH_TAG = "policy.sha256"

#: Config subtrees left out of the params: the plant models (fixed by the data hash) and Hydra's.
EXCLUDED = ("systems.plants", "hydra")
MAX_VALUE = 6000  # MLflow's limit on a param value

#: How a sweep or a study hands its parent run to the training runs it starts.
PARENT_RUN_ENV = "GC_PARENT_RUN_ID"
SWEEP_ENV = "GC_SWEEP_NAME"

#: Run tags naming the process that runs a training, and its last sign of life.
HOST_TAG, PID_TAG, START_TAG, HEARTBEAT_TAG = "gc.host", "gc.pid", "gc.pid_start", "gc.heartbeat"

#: What a database says when a row another process inserted first is inserted again.
_CLASH = ("unique", "duplicate key", "duplicate entry", "integrity")


def swap_env(values: Mapping[str, str | None]) -> dict[str, str | None]:
    """Set environment variables (``None``: unset them); return their previous values."""
    saved = {key: os.environ.get(key) for key in values}
    for key, value in values.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value
    return saved


def tracking_uri(logger: Mapping[str, Any]) -> str:
    """The tracking URI from ``logger.tracking_uri`` (default: the embedded SQLite store)."""
    return str(logger.get("tracking_uri") or "sqlite:///mlflow.db")


def set_tracking(logger: Mapping[str, Any]) -> str:
    """Point MLflow at the ``logger`` config's tracking URI, its store initialised; return it."""
    import mlflow

    uri = tracking_uri(logger)
    mlflow.set_tracking_uri(uri)
    init_store(uri)
    return uri


def _sqlite_file(uri: str) -> Path | None:
    """The database file of an ``sqlite:///<path>`` URI (None for other stores, memory)."""
    if not uri.startswith("sqlite:///"):
        return None
    path = uri[len("sqlite:///") :].split("?", 1)[0]
    return Path(path) if path and path != ":memory:" and not path.startswith("file:") else None


@contextmanager
def store_lock(uri: str) -> Iterator[None]:
    """An exclusive lock on an SQLite store (``<db>.lock`` beside it); a no-op for others.

    Held while a new database's schema is made and while an experiment is found or made.
    """
    db = _sqlite_file(uri)
    if db is None or not db.parent.is_dir():
        yield
        return
    with open(db.with_name(db.name + ".lock"), "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)  # released when the file closes
        yield


_INITIALISED: set[str] = set()


def init_store(uri: str) -> None:
    """Create (or migrate) a local SQLite store's schema once per process, under the lock."""
    import mlflow

    if uri in _INITIALISED or _sqlite_file(uri) is None:
        return
    with store_lock(uri):
        mlflow.MlflowClient(uri).search_experiments(max_results=1)
    _INITIALISED.add(uri)


def flatten_params(tree: ConfigTree, exclude: tuple[str, ...] = EXCLUDED) -> dict[str, str]:
    """Flatten ``tree`` into ``{"a.b.c": "value"}``; lists become JSON; redacted.

    Examples
    --------
    >>> flatten_params({"model": {"hidden": 64}, "experts": 5, "hydra": {"x": 1}})
    {'model.hidden': '64', 'experts': '5'}
    """
    out: dict[str, str] = {}

    def walk(node: Any, prefix: str) -> None:
        if prefix in exclude:
            return
        if isinstance(node, Mapping):
            for key, value in node.items():
                walk(value, f"{prefix}.{key}" if prefix else str(key))
        else:
            text = json.dumps(node) if isinstance(node, list | tuple) else str(node)
            out[prefix] = redact(text)[:MAX_VALUE]

    walk(tree, "")
    return out


def dvc_data_version(data_dir: str | Path) -> str | None:
    """DVC's hash of ``data_dir`` as recorded in ``dvc.lock`` (an ``outs`` entry), if any."""
    lock = Path("dvc.lock")
    if not lock.is_file():
        return None
    target = Path(data_dir).as_posix().rstrip("/")
    stages = (yaml.safe_load(lock.read_text()) or {}).get("stages", {})
    for stage in stages.values():
        for out in stage.get("outs", []):
            if str(out.get("path", "")).rstrip("/") == target:
                return out.get("md5") or out.get("hash")
    return None


@contextmanager
def mlflow_run(logger: Mapping[str, Any], kind: str = "train") -> Iterator[mlflow.ActiveRun]:
    """A new fluent run for work other than training, in the experiment of ``kind``.

    Nested under the environment's parent (:func:`parent_run_tags`), tagged with this process;
    stale runs of this host are ended first.
    """
    import mlflow

    exp_id = experiment_id(logger, kind=kind)
    end_stale_runs(exp_id)
    tags = {**parent_run_tags(), **process_tags()}
    run_name = redact(logger.get("run_name"))
    with mlflow.start_run(experiment_id=exp_id, run_name=run_name, tags=tags) as run:
        yield run


def _store_error(uri: str, what: str, detail: str) -> ConnectionError:
    """The error for a store that fails, naming the setting, carrying no credential."""
    return ConnectionError(
        f"the MLflow tracking store {redact(uri)} (logger.tracking_uri) {what}: "
        f"{redact(detail)[:500]}. Check that it runs and the URI is right, or point "
        "logger.tracking_uri (or MLFLOW_TRACKING_URI) at another store, e.g. sqlite:///mlflow.db"
    )


#: MLflow's settings of a request to a tracking server, set for :func:`check_store`'s one try.
_ONE_TRY = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0", "MLFLOW_HTTP_REQUEST_TIMEOUT": "20"}


def check_store(logger: Mapping[str, Any]) -> str:
    """Point MLflow at ``logger``'s store and refuse one that does not answer; its URI.

    One request without MLflow's minutes of retries, before any work is written.

    Raises
    ------
    ConnectionError
        If the store does not answer or refuses (naming ``logger.tracking_uri``, masked).
    """
    import mlflow

    uri = tracking_uri(logger)
    saved = swap_env(_ONE_TRY)
    try:
        set_tracking(logger)
        mlflow.MlflowClient(uri).search_experiments(max_results=1)
    except Exception as e:  # noqa: BLE001 - whatever the store raised, named and masked
        raise _store_error(uri, "does not answer", str(e)) from None
    finally:
        swap_env(saved)
    return uri


def experiment_name(logger: Mapping[str, Any], kind: str) -> str:
    """``logger.experiment_name`` if set, else ``<logger.experiment_prefix>/<kind>``.

    Raises
    ------
    ValueError
        If ``kind`` is not one of :data:`KINDS`.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown kind of work {kind!r}; expected one of {', '.join(KINDS)}")
    explicit = logger.get("experiment_name")
    if explicit:
        return str(explicit)
    prefix = str(logger.get("experiment_prefix") or DEFAULT_PREFIX)
    return f"{prefix}/{kind}"


def experiment_id(logger: Mapping[str, Any], kind: str = "train") -> str:
    """Point MLflow at ``logger``'s store; the id of the experiment of ``kind``, made if missing.

    Lookup and creation hold :func:`store_lock`; the experiment gets ``KIND_TAG``.

    Raises
    ------
    ConnectionError
        If the store fails (the message carries no credential).
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    uri = set_tracking(logger)
    name = experiment_name(logger, kind)
    with store_lock(uri):
        try:
            experiment = mlflow.get_experiment_by_name(name)
        except MlflowException as e:
            raise _store_error(uri, "failed", e.message) from None
        if experiment is None:
            location = logger.get("artifact_location")
            local = uri.startswith(("sqlite:", "file:")) or "://" not in uri
            if location and local and "://" not in str(location):
                location = Path(location).resolve().as_uri()
            try:
                return mlflow.create_experiment(
                    name, artifact_location=location or None, tags=dict([KIND_TAG])
                )
            except MlflowException:
                experiment = mlflow.get_experiment_by_name(name)  # another worker made it first
                if experiment is None:
                    raise
        tag_kind(experiment)
        return experiment.experiment_id


def tag_kind(experiment: Any) -> None:
    """Tag an MLflow experiment made without it as model development (``KIND_TAG``)."""
    import mlflow

    if experiment.tags.get(KIND_TAG[0]) is None:
        mlflow.MlflowClient().set_experiment_tag(experiment.experiment_id, *KIND_TAG)


def now() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def process_tags() -> dict[str, str]:
    """``gc.host``, ``gc.pid``, ``gc.pid_start`` (the kernel's start time) and a heartbeat."""
    start = process_start(os.getpid())
    tags = {HOST_TAG: socket.gethostname(), PID_TAG: str(os.getpid()), HEARTBEAT_TAG: now()}
    return tags if start is None else {**tags, START_TAG: start}


def end_stale_runs(exp_id: str) -> list[str]:
    """Set ``KILLED`` the ``RUNNING`` runs of ``exp_id`` whose process on this host is gone.

    A run killed outright (SIGKILL, out of memory) cannot end itself; its ``gc.host`` and
    ``gc.pid`` tags name its process. Each gets the tag ``gc.killed_reason``; returns their ids.
    """
    import mlflow

    host = socket.gethostname()
    client = mlflow.MlflowClient()
    runs = client.search_runs(
        [exp_id],
        filter_string=f"attributes.status = 'RUNNING' and tags.`{HOST_TAG}` = '{host}'",
        max_results=1000,
    )
    ended = []
    for found in runs:
        with store_lock(mlflow.get_tracking_uri()):
            run = client.get_run(found.info.run_id)  # again: it may have been reopened since
            tags = run.data.tags
            pid = int(tags.get(PID_TAG, "0") or 0)
            if run.info.status != "RUNNING" or pid <= 0 or pid_alive(pid, tags.get(START_TAG)):
                continue
            beat, me = tags.get(HEARTBEAT_TAG, "?"), f"{host}:{os.getpid()}"
            reason = (
                f"process {host}:{pid} is gone (last heartbeat {beat}); ended by {me} at {now()}"
            )
            client.set_tag(run.info.run_id, "gc.killed_reason", reason)
            client.set_terminated(run.info.run_id, "KILLED")
        log.warning("MLflow run %s was left RUNNING: %s; set KILLED", run.info.run_id, reason)
        ended.append(run.info.run_id)
    return ended


def parent_run_tags() -> dict[str, str]:
    """Tags that nest a new run under the parent run named by ``GC_PARENT_RUN_ID``, if set.

    ``mlflow.parentRunId`` nests it in the MLflow UI; ``sweep`` is ``GC_SWEEP_NAME``.
    """
    parent = os.environ.get(PARENT_RUN_ENV)
    if not parent:
        return {}
    tags = {"mlflow.parentRunId": parent}
    if os.environ.get(SWEEP_ENV):
        tags["sweep"] = os.environ[SWEEP_ENV]
    return tags


def retry_on_clash(call: Any, *args: Any, attempts: int = 6, **kwargs: Any) -> Any:
    """``call(*args, **kwargs)``, again after a short random wait when a row insert clashed.

    MLflow's SQL store inserts a missing row after an unlocked read: of two writers, one fails
    on the unique key, and once more finds the row. Other errors, or ``attempts`` clashes, raise.
    """
    from mlflow.exceptions import MlflowException

    for attempt in range(1, attempts + 1):
        try:
            return call(*args, **kwargs)
        except MlflowException as exc:
            text = str(exc).lower()
            if attempt == attempts or not any(s in text for s in _CLASH):
                raise
            log.info("a row another process wrote at the same time: trying again")
            time.sleep(random.uniform(0.05, 0.3) * attempt)
    return None


def find_training_run(sha256: str) -> str | None:
    """The newest finished run that wrote the policy ``sha256`` (tag :data:`POLICY_HASH_TAG`)."""
    import mlflow

    runs = mlflow.search_runs(
        search_all_experiments=True,
        filter_string=f"tags.`{POLICY_HASH_TAG}` = '{sha256}' and attributes.status = 'FINISHED'",
        order_by=["attributes.start_time DESC"],
        max_results=1,
        output_format="list",
    )
    return runs[0].info.run_id if runs else None
