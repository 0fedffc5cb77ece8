"""Which runs the ablation report compares, and the check that they are comparable.

Runs that differ in more than d and M (and ``report.identity_keys``) say nothing about d or M.
"""

from __future__ import annotations

import fnmatch
import logging
from collections.abc import Mapping, Sequence
from typing import Any

from generalist_control.common.secrets import redact
from generalist_control.reports.report_settings import ReportSettings
from generalist_control.reports.runs import (
    SWEEP_COMMANDS,
    ByConfig,
    NoAblationRunsError,
    RunPoint,
    Sweeps,
    runs_from_mlflow,
    seed_runs,
    select_sweeps,
)
from generalist_control.tracking.mlflow_utils import experiment_name
from generalist_control.tracking.parents import find_parents

__all__ = [
    "SWEPT_KEYS",
    "MixedRunsError",
    "check_comparable",
    "differing_params",
    "parents_hint",
    "resolve_parents",
    "select_runs",
]

log = logging.getLogger(__name__)

#: The report's axes: the params its runs may differ in.
SWEPT_KEYS = ("model.hidden", "experts", "model.experts")  # model.experts is ${experts}
_ABSENT = "(not logged)"


class MixedRunsError(ValueError):
    """The runs the report would compare differ in more than the swept keys."""


def parents_hint(client: Any, exp_id: str, limit: int = 5) -> str:
    """The newest parent runs of the experiment, ``<id> '<name>'``, for messages."""
    found = find_parents(client, exp_id)[::-1][:limit]
    if not found:
        return "none"
    return ", ".join(f"{r.info.run_id} {r.info.run_name!r}" for r in found)


def resolve_parents(
    client: Any, exp_id: str, parent_run: Sequence[str] | None
) -> list[str] | None:
    """The parent run ids ``report.parent_run`` names (ids or names, the newest of a name).

    Raises
    ------
    LookupError
        A name or id that is no parent run of the experiment (the message lists some).
    """
    if not parent_run:
        return None
    parents = find_parents(client, exp_id)[::-1]
    ids = []
    for item in parent_run:
        match = next((r for r in parents if item in (r.info.run_id, r.info.run_name)), None)
        if match is None:
            raise LookupError(
                f"report.parent_run: {item!r} is no sweep or study parent run of the "
                f"experiment {exp_id}; its newest parent runs: {parents_hint(client, exp_id)}"
            )
        ids.append(match.info.run_id)
    return ids


def differing_params(
    points: Sequence[RunPoint], identity: Sequence[str]
) -> dict[str, dict[str, list[RunPoint]]]:
    """``{key: {value: [runs]}}`` of the params (not swept or identity) the runs disagree on."""
    keys = sorted({k for p in points for k in p.params if k not in SWEPT_KEYS})
    keys = [k for k in keys if not any(fnmatch.fnmatchcase(k, pat) for pat in identity)]
    out: dict[str, dict[str, list[RunPoint]]] = {}
    for key in keys:
        groups: dict[str, list[RunPoint]] = {}
        for p in points:
            groups.setdefault(str(p.params.get(key, _ABSENT)), []).append(p)
        if len(groups) > 1:
            out[key] = groups
    return out


def _describe(diff: Mapping[str, Mapping[str, Sequence[RunPoint]]]) -> str:
    lines = []
    for key, groups in diff.items():
        parts = [
            f"{value!r} in " + ", ".join(f"{p.run_name} ({p.run_id})" for p in runs)
            for value, runs in groups.items()
        ]
        lines.append(f"  {key}: " + "; ".join(parts))
    return "\n".join(lines)


def check_comparable(
    points: Sequence[RunPoint],
    identity: Sequence[str],
    allow_mixed: bool = False,
    parents: str = "none",
) -> dict[str, dict[str, list[str]]]:
    """Refuse (or warn, ``allow_mixed``) runs that differ in more than the swept keys.

    ``identity``: glob patterns of params that may differ (``report.identity_keys``);
    ``parents``: the experiment's parent runs, quoted in the fix (:func:`parents_hint`).
    Returns ``{key: {value: [run ids]}}`` of the differences let through.

    Raises
    ------
    MixedRunsError
        On a difference, unless ``allow_mixed``.
    """
    diff = differing_params(points, identity)
    if not diff:
        return {}
    head = (
        f"the {len(points)} runs the report would compare differ in more than the swept "
        f"keys ({', '.join(SWEPT_KEYS)}):\n{_describe(diff)}\n"
    )
    key, value = next(
        ((k, v) for k, g in diff.items() for v in g if v != _ABSENT), ("trainer.max_epochs", "30")
    )
    fixes = (
        f"Compare runs of one configuration: choose the sweeps with report.parent_run=<id or "
        f"name> or a list of them (newest parent runs: {parents}), or narrow the runs with "
        f"report.filter_string, e.g. \"attributes.status = 'FINISHED' and "
        f"params.`{key}` = '{value}'\""
    )
    if not allow_mixed:
        raise MixedRunsError(f"{head}{fixes}; or report them anyway with report.allow_mixed=true.")
    log.warning("MIXED RUNS (report.allow_mixed=true): %s%s.", head, fixes)
    return {k: {v: [p.run_id for p in runs] for v, runs in g.items()} for k, g in diff.items()}


def select_runs(
    settings: ReportSettings, logger: Mapping[str, Any], client: Any
) -> tuple[str, Sweeps, dict[str, dict[str, list[str]]], ByConfig]:
    """The report's experiment, its sweep points, the differences let through, every seed.

    Raises
    ------
    NoAblationRunsError
        No training run in the experiment (or under the parents) passes the filter.
    LookupError
        ``report.parent_run`` names no parent run of the experiment.
    MixedRunsError
        See :func:`check_comparable`.
    """
    experiment = settings.experiment_name or experiment_name(logger, "sweep")
    found = client.get_experiment_by_name(experiment)
    exp_id = found.experiment_id if found is not None else None
    parents = resolve_parents(client, exp_id, settings.parent_run) if exp_id else None
    points = runs_from_mlflow(experiment, settings.filter_string, client, parents)
    if not points:
        where = f" under the parent runs {parents}" if parents else ""
        raise NoAblationRunsError(
            f"no finished training run in MLflow experiment '{experiment}'{where} at "
            f"{redact(str(client.tracking_uri))} (filter: {settings.filter_string!r}). "
            "Create the ablation runs with:\n  " + "\n  ".join(SWEEP_COMMANDS)
        )
    base = settings.baseline
    sweeps = select_sweeps(points, settings.hidden, settings.experts, (base.hidden, base.experts))
    by_config = seed_runs(points, sweeps)
    mixed = check_comparable(
        [p for runs in by_config.values() for p in runs],
        settings.identity_keys,
        settings.allow_mixed,
        parents_hint(client, exp_id) if exp_id else "none",
    )
    return experiment, sweeps, mixed, by_config
