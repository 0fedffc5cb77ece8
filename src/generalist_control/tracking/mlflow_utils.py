"""MLflow: the store, its experiments, the params of a training, and safety.

By default runs go to an embedded store in the working directory, an SQLite database
(``sqlite:///mlflow.db``) plus an artifact folder (``mlruns/``), which ``mlflow ui`` run in
the repository shows. ``logger.tracking_uri`` (or ``MLFLOW_TRACKING_URI``) points it at a
server instead; the server then decides where artifacts go.

A training's run is opened by Lightning's ``MLFlowLogger``
(:mod:`~generalist_control.tracking.training_run`); it records the config keys that shaped
the training as params (:func:`training_params`), the data's content hash, per-epoch
metrics, and artifacts logged by :mod:`generalist_control.training.outputs`. Runs of other
work (an evaluation logging into its model's run, a report) are opened by
:func:`mlflow_run`. Experiments are named per kind of work
(:func:`~generalist_control.tracking.experiments.experiment_name`).

Safety: a fresh SQLite store is initialised under a file lock beside the database
(:func:`store_lock`), so trainings started together do not race on its schema; every param
is passed through :func:`generalist_control.common.secrets.redact`; and each training run is
tagged with its process (``gc.host``, ``gc.pid``, a heartbeat), so that the next training on
the same host ends a run whose process died without ending it (:func:`end_stale_runs`).
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import socket
from collections.abc import Iterator, Mapping
from contextlib import AbstractContextManager, contextmanager, nullcontext
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from generalist_control.common.secrets import redact
from generalist_control.tracking.experiments import experiment_name

if TYPE_CHECKING:
    import mlflow

__all__ = [
    "PARENT_RUN_ENV",
    "SWEEP_ENV",
    "dvc_data_version",
    "end_stale_runs",
    "experiment_id",
    "flatten_params",
    "init_store",
    "mlflow_run",
    "now",
    "parent_run_tags",
    "process_tags",
    "set_tracking",
    "store_lock",
    "tracking_uri",
]

log = logging.getLogger(__name__)

#: Config subtrees left out of the params: the plant models (fixed by the data hash, and in
#: the logged manifest) and Hydra's own settings.
EXCLUDED = ("systems.plants", "hydra")
MAX_VALUE = 6000  # MLflow's limit on a param value

#: Environment variables through which a sweep (``python train.py -m``) or a study
#: (:mod:`generalist_control.tune`) hands its parent run to the training runs it starts.
PARENT_RUN_ENV = "GC_PARENT_RUN_ID"
SWEEP_ENV = "GC_SWEEP_NAME"

#: Run tags naming the process that runs a training, and its last sign of life.
HOST_TAG, PID_TAG, START_TAG, HEARTBEAT_TAG = "gc.host", "gc.pid", "gc.pid_start", "gc.heartbeat"


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


def store_lock(uri: str) -> AbstractContextManager[None]:
    """An exclusive lock on an SQLite store (``<db>.lock`` beside it); a no-op for others.

    Held while a store is first initialised (MLflow creates or migrates the schema of a new
    database on first use, which two processes must not do at once) and while the
    experiment is looked up or created.
    """
    db = _sqlite_file(uri)
    if db is None or not db.parent.is_dir():
        return nullcontext()
    return _flock(db.with_name(db.name + ".lock"))


@contextmanager
def _flock(path: Path) -> Iterator[None]:
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


_INITIALISED: set[str] = set()


def init_store(uri: str) -> None:
    """Create (or migrate) the schema of a local SQLite store once, under :func:`store_lock`.

    Other stores are left to their server; a store is initialised once per process.
    """
    import mlflow

    if uri in _INITIALISED or _sqlite_file(uri) is None:
        return
    with store_lock(uri):
        mlflow.MlflowClient(uri).search_experiments(max_results=1)
    _INITIALISED.add(uri)


def _is_local(uri: str) -> bool:
    return uri.startswith(("sqlite:", "file:")) or "://" not in uri


def flatten_params(cfg: Mapping[str, Any], exclude: tuple[str, ...] = EXCLUDED) -> dict[str, str]:
    """Flatten a (resolved) config into ``{"a.b.c": "value"}``; lists become JSON.

    Passwords in URLs are masked (:func:`generalist_control.common.secrets.redact`).

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

    walk(cfg, "")
    return out


def dvc_data_version(data_dir: str | Path, lock: str | Path = "dvc.lock") -> str | None:
    """DVC's hash of ``data_dir`` as recorded in ``dvc.lock`` (an ``outs`` entry), if any."""
    lock = Path(lock)
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
def mlflow_run(
    logger: Mapping[str, Any], resume_run_id: str | None = None, kind: str = "train"
) -> Iterator[mlflow.ActiveRun]:
    """Open a run with the fluent API: ``resume_run_id``'s, if it exists, else a new one.

    For work other than training (a training's run is Lightning's, see
    :mod:`~generalist_control.tracking.training_run`): an evaluation logging into the
    model's run, a report.

    Parameters
    ----------
    logger : mapping
        The ``logger`` config: ``tracking_uri``, ``experiment_name``, ``artifact_location``
        (used when creating the experiment in a local store), ``run_name``.
    resume_run_id : str, optional
        Run to continue (e.g. the evaluated model's).
    kind : str
        The kind of work, which names the experiment of a new run
        (:func:`~generalist_control.tracking.experiments.experiment_name`).

    Notes
    -----
    Inside a sweep or an Optuna study, a new run is nested under the parent run given by
    the environment (:func:`parent_run_tags`). Before a new run opens, runs of this host
    whose process is gone are ended (:func:`end_stale_runs`); a run continued
    (``resume_run_id``, e.g. an evaluation logging into its model's run, two of which may
    run side by side in the ablation) leaves that to the next new run. The run is tagged
    with this process (:func:`process_tags`).
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    exp_id = experiment_id(logger, kind=kind)
    if not resume_run_id:  # a process that continues a run leaves the others alone
        end_stale_runs(exp_id)
    run_id = None
    if resume_run_id:
        try:
            run_id = mlflow.get_run(resume_run_id).info.run_id
        except MlflowException:
            run_id = None  # the checkpoint comes from another store: start a new run
    with store_lock(mlflow.get_tracking_uri()):  # reopened, it has old tags until set_tags
        run = mlflow.start_run(
            run_id=run_id,
            experiment_id=None if run_id else exp_id,
            run_name=None if run_id else redact(logger.get("run_name")),
            tags=None if run_id else parent_run_tags() or None,
        )
        mlflow.set_tags(process_tags())
    with run:
        yield run


def _lookup(uri: str, name: str) -> Any:
    """The experiment ``name`` (None if missing); a store that fails is named, redacted.

    Raises
    ------
    ConnectionError
        If the store does not answer (or refuses); message and error carry no credential.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    try:
        return mlflow.get_experiment_by_name(name)
    except MlflowException as e:
        raise ConnectionError(
            f"the MLflow tracking store {redact(uri)} (logger.tracking_uri) failed: "
            f"{redact(e.message)}. Check that it runs and the URI is right, or point "
            "logger.tracking_uri (or MLFLOW_TRACKING_URI) at another store, e.g. "
            "sqlite:///mlflow.db"
        ) from None


def experiment_id(logger: Mapping[str, Any], kind: str = "train") -> str:
    """Point MLflow at ``logger``'s store; the id of the experiment of ``kind``, made if missing.

    The name comes from :func:`~generalist_control.tracking.experiments.experiment_name`
    (``<logger.experiment_prefix>/<kind>``, or ``logger.experiment_name`` when set). Lookup
    and creation hold :func:`store_lock`.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    uri = set_tracking(logger)
    name = experiment_name(logger, kind)
    with store_lock(uri):
        experiment = _lookup(uri, name)
        if experiment is not None:
            return experiment.experiment_id
        location = logger.get("artifact_location")
        if location and _is_local(uri) and "://" not in str(location):
            location = Path(location).resolve().as_uri()
        try:
            return mlflow.create_experiment(name, artifact_location=location or None)
        except MlflowException:
            experiment = mlflow.get_experiment_by_name(name)  # another worker created it first
            if experiment is None:
                raise
            return experiment.experiment_id


def _proc_stat(pid: int) -> list[str] | None:
    """Fields 3.. of ``/proc/<pid>/stat`` (state, ..., start time at [19]); None if absent."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text.rsplit(")", 1)[1].split()


def now() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def process_tags() -> dict[str, str]:
    """``gc.host``, ``gc.pid``, ``gc.pid_start`` (the kernel's start time) and a heartbeat."""
    stat = _proc_stat(os.getpid())
    tags = {HOST_TAG: socket.gethostname(), PID_TAG: str(os.getpid()), HEARTBEAT_TAG: now()}
    if stat is not None:
        tags[START_TAG] = stat[19]
    return tags


def _alive(pid: int, start: str | None) -> bool:
    """Whether process ``pid`` (started at ``start``, if known) still runs on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # it exists, under another user
    stat = _proc_stat(pid)
    if stat is None:
        return True  # no /proc: trust the signal
    return stat[0] != "Z" and (not start or stat[19] == start)  # a zombie, a reused pid


def end_stale_runs(exp_id: str) -> list[str]:
    """Set ``KILLED`` the ``RUNNING`` runs of ``exp_id`` whose process on this host is gone.

    A training killed outright (SIGKILL, out of memory) cannot end its run; its ``gc.host``
    and ``gc.pid`` tags say which process ran it (runs of this host only). Each ended run
    gets the tag ``gc.killed_reason``. Returns their ids.
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
            if run.info.status != "RUNNING" or pid <= 0 or _alive(pid, tags.get(START_TAG)):
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
    """Tags that file a new run under the parent run named by ``GC_PARENT_RUN_ID``, if set.

    ``mlflow.parentRunId`` nests the run under its sweep (or study) in the MLflow UI;
    ``sweep`` carries the sweep's name (``GC_SWEEP_NAME``).
    """
    parent = os.environ.get(PARENT_RUN_ENV)
    if not parent:
        return {}
    tags = {"mlflow.parentRunId": parent}
    if os.environ.get(SWEEP_ENV):
        tags["sweep"] = os.environ[SWEEP_ENV]
    return tags
