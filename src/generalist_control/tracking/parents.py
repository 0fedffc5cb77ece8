"""Parent runs: one MLflow run that groups the training runs of a sweep or a study.

A parent is created with :func:`create_parent_run` (a multirun's, a study's) or found by
name with :func:`named_parent` (a group of separate commands, e.g. the DVC ablation's
trainings); inside :func:`parent_run` (or with ``GC_PARENT_RUN_ID`` set) every training run
is filed under it (:func:`generalist_control.tracking.mlflow_utils.parent_run_tags`), and
:func:`summarise_children` logs the best child to the parent.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

from generalist_control.common.secrets import redact
from generalist_control.tracking import mlflow_utils

__all__ = [
    "GROUP_ROLE",
    "ROLE_TAG",
    "create_parent_run",
    "export_parent",
    "named_parent",
    "parent_run",
    "restore_parent",
    "summarise_children",
]

#: Tag that marks a parent run and says what it groups (``sweep``, ``study`` or ``group``).
ROLE_TAG = "gc.role"
#: The role of a parent found or made by name (:func:`named_parent`).
GROUP_ROLE = "group"
_NAME = re.compile(r"[A-Za-z0-9_.:=,/+@ -]+")


def create_parent_run(
    logger: Mapping[str, Any],
    name: str,
    role: str,
    tags: Mapping[str, str] | None = None,
) -> str:
    """Create a ``RUNNING`` parent run in ``logger``'s experiment; return its id.

    Parameters
    ----------
    logger : mapping
        The ``logger`` config (tracking URI, experiment name, artifact location).
    name : str
        Run name, shown in the MLflow UI; also the children's ``sweep`` tag.
    role : str
        What the parent groups: ``"sweep"`` (a multirun) or ``"study"`` (Optuna).
    tags : mapping, optional
        Further tags of the parent run.
    """
    import mlflow

    name = redact(name)
    exp_id = mlflow_utils.experiment_id(logger)
    run = mlflow.MlflowClient().create_run(
        exp_id, run_name=name, tags={ROLE_TAG: role, "sweep": name, **(tags or {})}
    )
    return run.info.run_id


def _named(client: Any, exp_id: str, name: str) -> list[Any]:
    """The group parents of an experiment called ``name``, oldest first."""
    runs = client.search_runs(
        [exp_id],
        filter_string=f"tags.`{ROLE_TAG}` = '{GROUP_ROLE}' and attributes.run_name = '{name}'",
        order_by=["attributes.start_time ASC"],
        max_results=100,
    )
    return sorted(runs, key=lambda r: (r.info.start_time, r.info.run_id))


def named_parent(logger: Mapping[str, Any], name: str, kind: str = "train") -> str:
    """The id of the parent run called ``name`` in the experiment of ``kind``, made if missing.

    Separate commands that give the same name (the DVC ablation's trainings, two at a time)
    share one parent: on an SQLite store the lookup and the creation hold the store's lock;
    on a server two commands may both create one, and then both keep the older and the other
    is deleted. The parent is ``FINISHED`` at once (a row that groups, with no work of its
    own) and tagged ``gc.role = group``.

    Parameters
    ----------
    logger : mapping
        The ``logger`` config (tracking URI, experiment name or prefix).
    name : str
        Letters, digits, spaces and ``_.:=,/+@-`` (it goes into a search filter).
    kind : str
        The kind of work whose experiment holds the parent (that of the runs it groups).

    Raises
    ------
    ValueError
        For a name with other characters.
    """
    import mlflow

    if not _NAME.fullmatch(name):
        raise ValueError(
            f"parent run name {name!r}: use letters, digits, spaces and _.:=,/+@- only"
        )
    exp_id = mlflow_utils.experiment_id(logger, kind)
    client = mlflow.MlflowClient()
    with mlflow_utils.store_lock(mlflow.get_tracking_uri()):
        found = _named(client, exp_id, name)
        if found:
            return str(found[0].info.run_id)
        mine = client.create_run(
            exp_id, run_name=name, tags={ROLE_TAG: GROUP_ROLE, "sweep": name}
        ).info.run_id
        client.set_terminated(mine, "FINISHED")
    oldest = str(_named(client, exp_id, name)[0].info.run_id)
    if oldest != mine:  # another command made one at the same time (a server store)
        client.delete_run(mine)
    return oldest


def export_parent(run_id: str, name: str) -> dict[str, str | None]:
    """New training runs are children of ``run_id`` (tag ``sweep=name``) from now on.

    Returns the previous values of ``GC_PARENT_RUN_ID`` and ``GC_SWEEP_NAME``, for
    :func:`restore_parent`.
    """
    keys = (mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV)
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update(dict(zip(keys, (run_id, name), strict=True)))
    return saved


def restore_parent(saved: Mapping[str, str | None]) -> None:
    """The parent variables as :func:`export_parent` found them."""
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@contextmanager
def parent_run(run_id: str, name: str) -> Iterator[None]:
    """Within the block, new training runs are children of ``run_id`` (tag ``sweep=name``)."""
    saved = export_parent(run_id, name)
    try:
        yield
    finally:
        restore_parent(saved)


def summarise_children(parent_id: str, metric: str) -> dict:
    """Log a summary of the parent's child runs to the parent; return it.

    Parameters
    ----------
    parent_id : str
        The parent run (its experiment is searched for runs tagged with it).
    metric : str
        The children's score (lower is better): their ``best/<metric>`` if logged, else
        ``<metric>``.

    Returns
    -------
    dict
        ``n_runs``, ``n_finished`` and, when a child has the metric, ``best_value`` and
        ``best_run_id``; logged as ``sweep/n_runs``, ``sweep/n_finished``,
        ``sweep/best/<metric>`` and the tag ``sweep.best_run_id``.
    """
    import mlflow

    client = mlflow.MlflowClient()
    parent = client.get_run(parent_id)
    children = client.search_runs(
        [parent.info.experiment_id],
        filter_string=f"tags.mlflow.parentRunId = '{parent_id}'",
        max_results=10_000,
    )
    summary: dict[str, Any] = {
        "n_runs": len(children),
        "n_finished": sum(c.info.status == "FINISHED" for c in children),
    }
    scored = []
    for child in children:
        value = child.data.metrics.get(f"best/{metric}", child.data.metrics.get(metric))
        if value is not None and math.isfinite(value):
            scored.append((value, child.info.run_id))
    metrics = {"sweep/n_runs": summary["n_runs"], "sweep/n_finished": summary["n_finished"]}
    if scored:
        best_value, best_id = min(scored)
        summary.update(best_value=best_value, best_run_id=best_id)
        metrics[f"sweep/best/{metric}"] = best_value
        client.set_tag(parent_id, "sweep.best_run_id", best_id)
    for key, value in metrics.items():
        client.log_metric(parent_id, key, float(value))
    return summary
