"""Writing an evaluation's outputs: CSV, tables, summary and plots, atomically, in one folder.

The folder (``paths.reports_dir``, default ``reports/eval``) is replaced as a whole
(:func:`~generalist_control.common.atomic.publish_directory`), and only if it holds nothing
but an evaluation's own outputs (:data:`OWNED`).
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
from generalist_control.evaluation import plots as plotting
from generalist_control.evaluation import tables
from generalist_control.evaluation.summary import summarise
from generalist_control.simulation.simulate import Trajectory

__all__ = ["OWNED", "check_reports_dir", "write_reports"]

#: What an evaluation folder holds: the only entries an evaluation may replace.
OWNED: dict[str, str | None] = {
    "metrics.csv": None,
    "summary.json": None,
    "table2.md": None,
    "table_all.md": None,
    "responses.csv": None,
    "plots": "*.png",
}


def check_reports_dir(out_dir: str | Path) -> None:
    """Refuse (before any work) a ``paths.reports_dir`` that holds other files."""
    check_replaceable(out_dir, OWNED, "paths.reports_dir")


def write_reports(
    df: pd.DataFrame,
    trajs: Mapping[str, Mapping[str, Mapping[str, Trajectory]]],
    out_dir: str | Path,
    plots: bool = True,
    bar: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the CSV, tables, summary and plots atomically to ``out_dir``; return the summary.

    ``bar`` overrides thresholds of the quality bar
    (:data:`~generalist_control.evaluation.summary.DEFAULT_BAR`).

    Raises
    ------
    generalist_control.common.atomic.ForeignDirectoryError
        If ``out_dir`` holds files an evaluation does not write; nothing is changed.
    """
    check_reports_dir(out_dir)
    with staging_directory(out_dir) as staging:
        df.to_csv(staging / "metrics.csv", index=False)
        summary = summarise(df, bar)
        (staging / "summary.json").write_text(json.dumps(strict(summary), indent=2) + "\n")
        (staging / "table2.md").write_text(tables.table2_markdown(df))
        (staging / "table_all.md").write_text(tables.table_all_markdown(df))
        tables.responses_csv(trajs).to_csv(staging / "responses.csv", index=False)
        if plots:
            plotting.plot_all(trajs, staging / "plots")
        publish_directory(staging, out_dir, OWNED, "paths.reports_dir")
    return summary
