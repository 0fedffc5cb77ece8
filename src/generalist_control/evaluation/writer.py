"""Writing an evaluation's outputs: CSV, tables, summary and plots, atomically, in one folder.

The folder (``paths.reports_dir``, default ``reports/eval``) is replaced as a whole
(:func:`~generalist_control.common.atomic.publish_directory`), and only if it holds nothing
but an evaluation's own outputs (:data:`OWNED`).

``summary.json`` holds the quality-bar figures in full; ``scores.json`` (the DVC metric of the
``evaluate`` stage) a handful of headline numbers in units that read well at
``dvc metrics show``'s default rounding to 5 decimals (:func:`headline_scores`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from generalist_control.common.atomic import (
    check_replaceable,
    publish_directory,
    staging_directory,
)
from generalist_control.common.jsonsafe import strict
from generalist_control.evaluation import tables
from generalist_control.evaluation.background import FigureJob
from generalist_control.evaluation.plots import plot_all
from generalist_control.evaluation.runner import STEP_KINDS
from generalist_control.evaluation.setpoint import setpoint_summary
from generalist_control.evaluation.summary import summarise
from generalist_control.simulation.simulate import Trajectory

__all__ = ["OWNED", "check_reports_dir", "headline_scores", "write_reports"]

#: What an evaluation folder holds: the only entries an evaluation may replace.
OWNED: dict[str, str | None] = {
    "metrics.csv": None,
    "summary.json": None,
    "scores.json": None,
    "table2.md": None,
    "table_all.md": None,
    "responses.csv": None,
    "setpoint.csv": None,
    "plots": "*.png",
}


def headline_scores(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The headline figures of a :func:`~generalist_control.evaluation.summary.summarise` result.

    ``diverged``: runs of a learned controller (GC, GC-AW) that diverged, all scenarios;
    ``bar_passed`` / ``bar_checked``: verdicts of the quality bar passed / measured;
    ``ISE_ratio``, ``ITAE_ratio``: worst GC/LQI ratio on the unit step; ``RMSE_ratio``: worst
    over the tracking scenarios; ``ess_ppm``: the worst relative steady-state error of GC on
    the step scenarios in parts per million (1e-6), so that errors down to 1e-11 do not round
    to 0.0. A figure that was not measured is ``None`` (``null``).
    """
    ratios, tracking = summary.get("ratios", {}), summary.get("tracking", {})
    step = ratios.get("step", {})
    ess = [ratios[s]["worst_relative_ess_GC"] for s in STEP_KINDS if s in ratios]
    rmse = [v["worst_RMSE_ratio"] for v in tracking.values()]
    verdicts = [v for v in summary.get("quality_bar", {}).values() if v is not None]
    diverged = summary.get("diverged", {})
    return {
        "diverged": sum(sum(diverged.get(c, {}).values()) for c in ("GC", "GC-AW")),
        "bar_passed": sum(bool(v) for v in verdicts),
        "bar_checked": len(verdicts),
        "ISE_ratio": step.get("worst_ISE_ratio"),
        "ITAE_ratio": step.get("worst_ITAE_ratio"),
        "RMSE_ratio": max(rmse) if rmse else None,
        "ess_ppm": 1e6 * max(ess) if ess else None,
    }


def check_reports_dir(out_dir: str | Path) -> None:
    """Refuse (before any work) a ``paths.reports_dir`` that holds other files."""
    check_replaceable(out_dir, OWNED, "paths.reports_dir")


def write_reports(
    df: pd.DataFrame,
    trajs: Mapping[str, Mapping[str, Mapping[str, Trajectory]]],
    out_dir: str | Path,
    plots: bool | FigureJob = True,
    bar: Mapping[str, Any] | None = None,
    setpoint: pd.DataFrame | None = None,
    record: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the CSV, tables, summary and plots atomically to ``out_dir``; return the summary.

    ``plots``: draw the figures (True), collect them from a job drawing them beside the
    evaluation (:class:`~generalist_control.evaluation.background.FigureJob`), or none.
    ``bar`` overrides thresholds of the quality bar
    (:data:`~generalist_control.evaluation.summary.DEFAULT_BAR`). ``setpoint``: the
    set-point check (:func:`~generalist_control.evaluation.setpoint.setpoint_stability`),
    written as ``setpoint.csv`` and summarised in ``summary.json``'s ``setpoint``.
    ``record``: which policy was evaluated, when and where
    (:mod:`~generalist_control.evaluation.provenance`: ``policy`` and ``provenance``),
    added to ``summary.json``.

    Raises
    ------
    generalist_control.common.atomic.ForeignDirectoryError
        If ``out_dir`` holds files an evaluation does not write; nothing is changed.
    """
    check_reports_dir(out_dir)
    with staging_directory(out_dir) as staging:
        df.to_csv(staging / "metrics.csv", index=False)
        summary = summarise(df, bar)
        if setpoint is not None:
            setpoint.to_csv(staging / "setpoint.csv", index=False)
            summary["setpoint"] = setpoint_summary(setpoint)
        summary.update(record or {})
        (staging / "summary.json").write_text(json.dumps(strict(summary), indent=2) + "\n")
        scores = strict(headline_scores(summary))
        (staging / "scores.json").write_text(json.dumps(scores, indent=2) + "\n")
        (staging / "table2.md").write_text(tables.table2_markdown(df))
        (staging / "table_all.md").write_text(tables.table_all_markdown(df))
        tables.responses_csv(trajs).to_csv(staging / "responses.csv", index=False)
        if isinstance(plots, FigureJob):
            plots.collect(staging / "plots")
        elif plots:
            plot_all(trajs, staging / "plots")
        publish_directory(staging, out_dir, OWNED, "paths.reports_dir")
    return summary
