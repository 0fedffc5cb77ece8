"""An evaluation's outputs in one folder, replaced as a whole under one lock.

Only a folder holding nothing but an evaluation's own outputs (:data:`OWNED`) is replaced;
the MLflow run gets the files of the snapshot it publishes.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

from generalist_control.common.atomic import (
    check_replaceable,
    publish_directory,
    staging_directory,
)
from generalist_control.common.jsonsafe import write_json
from generalist_control.evaluation import result_tables
from generalist_control.evaluation.eval_config import QualityBar
from generalist_control.evaluation.eval_run import EvalRun
from generalist_control.evaluation.forked_shares import fork_map
from generalist_control.evaluation.plots import plot_all
from generalist_control.evaluation.runner import Evaluation
from generalist_control.evaluation.setpoint import setpoint_summary
from generalist_control.evaluation.summary import LEARNED, summarise, worst_errors

__all__ = [
    "OWNED",
    "Record",
    "check_reports_dir",
    "headline_scores",
    "publish_snapshot",
    "write_reports",
]

#: What an evaluation folder holds: the only entries an evaluation may replace.
OWNED: dict[str, str | None] = {
    "metrics.csv": None,
    "summary.json": None,
    "scores.json": None,
    "provenance.json": None,
    "table2.md": None,
    "table_all.md": None,
    "responses.csv": None,
    "setpoint.csv": None,
    "plots": "*.png",
}

#: What the evaluation says of where it came from: ``summary`` (what reproduces, into
#: ``summary.json``) and ``provenance`` (the rest, into ``provenance.json``).
Record = Mapping[str, Mapping[str, Any]]


def headline_scores(summary: Mapping[str, Any]) -> dict[str, Any]:
    """``scores.json``: the headline figures of a :func:`.summarise` result (None: not measured).

    ``diverged`` (GC and GC-AW runs), ``bar_passed`` / ``bar_checked``, the worst ratios, and
    ``ess_ppm``: GC's worst relative steady-state error in parts per million, so that errors
    down to 1e-11 do not round to 0.0 at ``dvc metrics show``'s 5 decimals.
    """
    step = summary["ratios"].get("step", {})
    ess, rmse = worst_errors(summary)
    verdicts = [v for v in summary["quality_bar"].values() if v is not None]
    return {
        "diverged": sum(sum(summary["diverged"].get(c, {}).values()) for c in LEARNED),
        "bar_passed": sum(bool(v) for v in verdicts),
        "bar_checked": len(verdicts),
        "ISE_ratio": step.get("worst_ISE_ratio"),
        "ITAE_ratio": step.get("worst_ITAE_ratio"),
        "RMSE_ratio": max(rmse) if rmse else None,
        "ess_ppm": 1e6 * max(ess) if ess else None,
    }


def check_reports_dir(out_dir: str | Path, owned: Mapping[str, str | None] = OWNED) -> None:
    """Refuse (before any work) a ``paths.reports_dir`` that holds other files."""
    check_replaceable(out_dir, owned, "paths.reports_dir")


@contextmanager
def publish_snapshot(
    out_dir: Path, owned: Mapping[str, str | None], run: EvalRun | None
) -> Iterator[tuple[Path, dict[str, Any]]]:
    """Yield a staging folder and a summary to fill; on exit both are logged and published."""
    with staging_directory(out_dir) as staging:
        summary: dict[str, Any] = {}
        yield staging, summary
        if run is not None:
            run.log(summary, staging)
        publish_directory(staging, out_dir, owned, "paths.reports_dir")


def write_reports(
    ev: Evaluation,
    out_dir: str | Path,
    bar: QualityBar,
    record: Record,
    run: EvalRun | None = None,
    plots: bool = True,
) -> dict[str, Any]:
    """Write the CSV, tables, summary and figures of ``ev`` to ``out_dir``; return the summary.

    ``run``: the MLflow run that gets the same files and figures (None: none).

    Raises
    ------
    generalist_control.common.atomic.ForeignDirectoryError
        If ``out_dir`` holds files an evaluation does not write; nothing is changed.
    """
    out_dir = Path(out_dir)
    check_reports_dir(out_dir)
    with publish_snapshot(out_dir, OWNED, run) as (staging, summary):
        ev.metrics.to_csv(staging / "metrics.csv", index=False)
        summary.update(summarise(ev.metrics, bar))
        if ev.setpoint is not None:
            ev.setpoint.to_csv(staging / "setpoint.csv", index=False)
            summary["setpoint"] = setpoint_summary(ev.setpoint)
        summary.update(record["summary"])
        write_json(staging / "summary.json", summary)
        write_json(staging / "scores.json", headline_scores(summary))
        write_json(staging / "provenance.json", record["provenance"])
        (staging / "table2.md").write_text(result_tables.table2_markdown(ev.metrics))
        (staging / "table_all.md").write_text(result_tables.table_all_markdown(ev.metrics))
        result_tables.responses_csv(ev.trajectories).to_csv(staging / "responses.csv", index=False)
        if plots:
            draw = partial(plot_all, ev.trajectories, staging / "plots")
            fork_map(draw, [(0, 2), (1, 2)])
    return summary
