"""Parent runs: one MLflow run that groups the training runs of a sweep, a study or a group.

Inside :func:`parent_run` (or with ``GC_PARENT_RUN_ID`` set) every new training run is filed
under the parent; :func:`summarise_children` logs the best child to it.
"""

from __future__ import annotations

import math
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
    "find_parents",
    "named_parent",
    "parent_env",
    "parent_run",
    "summarise_children",
]

#: Tag that marks a parent run and says what it groups (``sweep``, ``study`` or ``group``).
ROLE_TAG = "gc.role"
#: The role of a parent found or made by name (:func:`named_parent`).
GROUP_ROLE = "group"
_NAME = re.compile(r"[A-Za-z0-9_.:=,/+@ -]+")


def create_parent_run(
    logger: Mapping[str, Any], name: str, role: str, tags: Mapping[str, str] | None = None
) -> str:
    """Create a ``RUNNING`` parent run in ``logger``'s experiment; return its id.

    ``name`` is also the children's ``sweep`` tag; ``role`` (``sweep``, ``study``) its
    :data:`ROLE_TAG`.
    """
    import mlflow

    name = redact(name)
    exp_id = mlflow_utils.experiment_id(logger)
    run = mlflow.MlflowClient().create_run(
        exp_id, run_name=name, tags={ROLE_TAG: role, "sweep": name, **(tags or {})}
    )
    return run.info.run_id


def find_parents(client: Any, exp_id: str, where: str = f"tags.`{ROLE_TAG}` != ''") -> list[Any]:
    """The parent runs of an experiment that match the MLflow filter ``where``, oldest first."""
    runs = client.search_runs([exp_id], filter_string=where, max_results=1000)
    runs = [r for r in runs if r.data.tags.get(ROLE_TAG)]
    return sorted(runs, key=lambda r: (r.info.start_time, r.info.run_id))


def _named(client: Any, exp_id: str, name: str) -> list[Any]:
    """The group parents of an experiment called ``name``, oldest first."""
    where = f"tags.`{ROLE_TAG}` = '{GROUP_ROLE}' and attributes.run_name = '{name}'"
    return find_parents(client, exp_id, where)


def named_parent(logger: Mapping[str, Any], name: str, kind: str = "train") -> str:
    """The id of the parent run called ``name`` in the experiment of ``kind``, made if missing.

    Separate commands that give the same name (the DVC ablation's trainings) share one
    parent, ``FINISHED`` at once and tagged ``gc.role = group``. On an SQLite store the
    lookup and creation hold the store's lock; on a server two commands may both create one,
    and both then keep the older.

    Raises
    ------
    ValueError
        For a name with characters other than letters, digits, spaces and ``_.:=,/+@-``.
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


def parent_env(run_id: str | None, name: str | None) -> dict[str, str | None]:
    """Environment that makes new training runs children of ``run_id`` (tag ``sweep=name``)."""
    return {mlflow_utils.PARENT_RUN_ENV: run_id, mlflow_utils.SWEEP_ENV: name}


@contextmanager
def parent_run(run_id: str, name: str) -> Iterator[None]:
    """Within the block, new training runs are children of ``run_id`` (tag ``sweep=name``)."""
    saved = mlflow_utils.swap_env(parent_env(run_id, name))
    try:
        yield
    finally:
        mlflow_utils.swap_env(saved)


def summarise_children(parent_id: str, metric: str) -> dict:
    """Log a summary of the parent's child runs to the parent; return it.

    ``n_runs``, ``n_finished`` and, when a child has the score (its ``best/<metric>``, else
    ``<metric>``; lower is better), ``best_value`` and ``best_run_id``; logged as
    ``sweep/n_runs``, ``sweep/n_finished``, ``sweep/best/<metric>`` and the tag
    ``sweep.best_run_id``.
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
