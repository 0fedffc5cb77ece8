"""The ablation report's own MLflow run: its outputs as artifacts, its figures as metrics."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mlflow
import numpy as np

from generalist_control.common.secrets import redact
from generalist_control.reports.runs import RUN_TYPE_TAG
from generalist_control.tracking import mlflow_utils

__all__ = ["log_report"]


def _metrics(summary: Mapping[str, Any]) -> dict[str, float]:
    """``report/missing_points``, ``ablation/<figure>/d32_M3``, ``claims/<verdict>``."""
    metrics = {"report/missing_points": float(len(summary["missing"]))}
    for label, fig in summary["configs"].items():
        key = label.replace("=", "").replace(",", "_")  # d32_M3
        for name in ("final_train_loss", "n_parameters", "mse_mean"):
            value = fig.get(name)
            if value is not None and np.isfinite(value):
                metrics[f"ablation/{name}/{key}"] = float(value)
    for verdict, count in (summary.get("claims_verdicts") or {}).items():
        metrics[f"claims/{verdict.replace(' ', '_')}"] = float(count)
    return metrics


def log_report(
    logger: Mapping[str, Any],
    params: Mapping[str, Any],
    run_name: str,
    experiment: str,
    out_dir: Path,
    summary: Mapping[str, Any],
) -> str:
    """Log the report as a run of the experiment of kind ``report``; return its run id.

    The run is tagged ``gc.run_type = report`` (the run search leaves it out), with the
    experiment it read (``report.source_experiment``) and, when ``report.allow_mixed`` let
    differing runs through, with the differences (``report.mixed_params``); ``params`` (the
    report's settings) are logged flat.
    """
    exp_id = mlflow_utils.experiment_id(logger, kind="report")
    with mlflow.start_run(experiment_id=exp_id, run_name=redact(run_name)) as active:
        mlflow.set_tags(
            {
                RUN_TYPE_TAG: "report",
                "report.kind": "ablation",
                "report.recipe": str(summary.get("recipe")),
                "report.missing": ", ".join(summary["missing"]) or "none",
                "report.source_experiment": experiment,
                "report.mixed_params": json.dumps(summary.get("mixed") or {})[:5000],
            }
        )
        mlflow.log_params(mlflow_utils.flatten_params(params))
        mlflow.log_dict(dict(summary), "ablation/summary.json")
        mlflow.log_artifacts(str(out_dir), "ablation")
        mlflow.log_metrics(_metrics(summary))
        return active.info.run_id
